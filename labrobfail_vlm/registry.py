"""The project's one registry: name -> spec (the class or factory and its default kwargs), with lazy imports.

In the style of ManiSkill's `register_env`: a decorator stores a spec, `make(name, **kwargs)` builds the entry with
its defaults under the caller's kwargs, and a name listed in `lazy` imports its module on first use (the module
registers itself), so heavy optional dependencies (a simulator, torch) stay unimported until asked for.

    POLICIES = Registry("policy", lazy={"act": "sim_backends.policies.act.policy"})

    @POLICIES.register("scripted")
    class ScriptedPolicy(Policy): ...

    POLICIES.make("act", checkpoint="runs/act/final")   # imports the ACT module on first use

Used for simulator backends and their task templates (sim_backends/registry.py), policies
(sim_backends/policies/base.py) and supervisors (sim_backends/supervision/base.py).
"""

from __future__ import annotations

import importlib
import json
from dataclasses import dataclass, field
from typing import Any, Callable


@dataclass(frozen=True)
class Spec:
    name: str
    cls: Any  # the class or factory
    kwargs: dict[str, Any] = field(default_factory=dict)  # defaults, JSON-serialisable (run records, workers)


class Registry:
    def __init__(
        self,
        kind: str,
        lazy: dict[str, str] | None = None,
        check: Callable[[Any], bool] | None = None,
        expects: str = "callable",
    ):
        self.kind = kind
        self.lazy = dict(lazy or {})  # name -> module that registers it on import
        self.check, self.expects = check or callable, expects
        self.specs: dict[str, Spec] = {}

    def register(self, name: str, **default_kwargs: Any) -> Callable:
        """Decorator for a class or factory selectable by `name`, with JSON-serialisable default kwargs."""
        try:
            json.dumps(default_kwargs)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{self.kind} {name!r}: default kwargs must be JSON-serialisable ({e})") from None

        def deco(obj: Any) -> Any:
            if not self.check(obj):
                raise ValueError(f"{self.kind} {name!r}: {obj!r} is not a {self.expects}")
            if name in self.specs and self.specs[name].cls is not obj:
                raise ValueError(f"{self.kind} {name!r} is already registered")
            self.specs[name] = Spec(name, obj, dict(default_kwargs))
            return obj

        return deco

    def names(self) -> list[str]:
        return sorted(set(self.lazy) | set(self.specs))

    def spec(self, name: str) -> Spec:
        if name not in self.specs and name in self.lazy:
            importlib.import_module(self.lazy[name])
        if name not in self.specs:
            raise ValueError(f"{self.kind}: unknown {self.kind} {name!r}; available: {', '.join(self.names())}")
        return self.specs[name]

    def get(self, name: str) -> Any:
        return self.spec(name).cls

    def make(self, name: str, **kwargs: Any) -> Any:
        s = self.spec(name)
        return s.cls(**{**s.kwargs, **kwargs})
