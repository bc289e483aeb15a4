"""Scenario files (configs/tasks/<backend>.yaml) read the same way by every backend.

A file has `templates` (name -> description, perturbation spec) and `scenarios` (name -> template,
params, layout, optional description/perturbations/substitutes). `ScenarioConfig` is the part of a
`FailureSource` that answers from it: scenario names without a simulator, a scenario's template and
perturbation spec, the task in words.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

from omegaconf import OmegaConf

from sim_backends.registry import task_templates


class ScenarioConfig:
    """Mixin (before FailureSource) for a backend whose scenarios live in a YAML file."""

    name: ClassVar[str]
    TASKS_FILE: ClassVar[Path]
    cfg: dict[str, Any]

    @classmethod
    def load_task_config(cls, path: str | Path | None = None) -> dict[str, Any]:
        cfg = OmegaConf.to_container(OmegaConf.load(path or cls.TASKS_FILE), resolve=True)
        assert isinstance(cfg, dict)
        cfg["scenarios"] = cls.expand_scenarios(cfg["scenarios"])
        known = task_templates(cls.name)
        for name, sc in cfg["scenarios"].items():
            if sc.get("template") not in known:
                raise ValueError(f"scenario {name}: unknown template {sc.get('template')!r}")
            cls.check_scenario(name, sc)
        return cfg

    @classmethod
    def expand_scenarios(cls, scenarios: dict[str, Any]) -> dict[str, Any]:
        """`expand: {role: [object, ...]}` turns one YAML entry into one scenario per object, named
        `<entry>_<object>` (the same layout and perturbations with another object in that role)."""
        out: dict[str, Any] = {}
        for name, sc in scenarios.items():
            if "expand" not in sc:
                out[name] = sc
                continue
            ((role, objects),) = sc["expand"].items()
            for obj in objects:
                layout = {**sc["layout"], role: {**sc["layout"][role], "object": obj}}
                out[f"{name}_{obj}"] = {k: v for k, v in sc.items() if k != "expand"} | {"layout": layout}
        return out

    @classmethod
    def check_scenario(cls, name: str, sc: dict[str, Any]) -> None:
        """A backend's own checks of one scenario entry (ValueError "scenario <name>: ...")."""

    @staticmethod
    def _repeat(cfg: dict[str, Any], sc: dict[str, Any]) -> int:
        """`repeat: N` (on a scenario or its template) puts it N times in each generation cycle."""
        return int(sc.get("repeat", cfg["templates"].get(sc["template"], {}).get("repeat", 1)))

    @classmethod
    def list_scenarios(cls, **kwargs: Any) -> list[str]:
        return list(cls.load_task_config(kwargs.get("tasks_file"))["scenarios"])

    @classmethod
    def scenario_repeats(cls, **kwargs: Any) -> dict[str, int]:
        cfg = cls.load_task_config(kwargs.get("tasks_file"))
        return {name: cls._repeat(cfg, sc) for name, sc in cfg["scenarios"].items()}

    def scenarios(self) -> list[str]:
        return list(self.cfg["scenarios"])

    def scenario_info(self, scenario: str) -> dict[str, Any]:
        sc = self._scenario(scenario)
        tmpl = self.cfg["templates"].get(sc["template"], {})
        return {
            "template": sc["template"],
            "perturbations": sc.get("perturbations", tmpl.get("perturbations", [])),
            "substitutes": sc.get("substitutes", {}),
            "repeat": self._repeat(self.cfg, sc),
        }

    def _scenario(self, scenario: str) -> dict[str, Any]:
        if scenario not in self.cfg["scenarios"]:
            raise ValueError(f"task: unknown scenario {scenario!r}")
        return self.cfg["scenarios"][scenario]

    def describe(self, scenario: str, labels: dict[str, str]) -> str:
        """The task in words (the `{task_name}` of the VQA preamble): the scenario's or its template's
        description with the scene's object words filled in."""
        sc = self._scenario(scenario)
        text = sc.get("description") or self.cfg["templates"].get(sc["template"], {}).get("description")
        return str(text or scenario.replace("_", " ")).format_map({**labels, **sc.get("params", {})})
