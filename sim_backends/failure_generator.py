"""FailureGenerator: tau~ = Phi_sem(Phi_ctrl(tau)) executed under Phi_phy(Psi).

Draws one perturbation from the scenario's config-driven spec and applies the
backend-agnostic operators; `run_pair` produces the paired success/failure
episodes from the identical seeded initial state.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from sim_backends.perturbations import control, physics, semantic
from sim_backends.perturbations.physics import PhysicsEvent
from sim_backends.source import FailureSource
from sim_backends.types import Episode, Keyframe


def apply_spec(spec: dict[str, Any], kfs: Sequence[Keyframe], positions: dict, rng: np.random.Generator
               ) -> tuple[list[Keyframe], list[PhysicsEvent], dict]:
    level, op = spec.get("level"), spec.get("op")
    if level == "control":
        names = spec.get("keyframes", [])
        if op == "translate":
            out, prov = control.translate(kfs, names, spec["sigma"], rng, float(spec.get("min_norm", 0.0)))
        elif op == "rotate":
            out, prov = control.rotate(kfs, names, spec["sigma"], rng, float(spec.get("min_norm", 0.0)))
        elif op == "corrupt_gripper":
            out, prov = control.corrupt_gripper(kfs, names, float(spec["lambda"]), rng)
        elif op == "truncate":
            out, prov = control.truncate(kfs, names, rng)
        else:
            raise ValueError(f"perturbation: unknown control op {op!r}")
        return out, [], {"level": level, **prov}
    if level == "physics":
        ev, prov = physics.sample_event(kfs, spec["param"], spec["target"], spec["at"], spec["delta"], rng)
        return list(kfs), [ev], {"level": level, **prov}
    if level == "semantic":
        if op == "permute":
            out, prov = semantic.permute(kfs, *spec["steps"])
        elif op == "omit":
            out, prov = semantic.omit(kfs, int(spec["step"]))
        elif op == "substitute":
            out, prov = semantic.substitute_target(kfs, int(spec["step"]), spec["to"], positions)
        else:
            raise ValueError(f"perturbation: unknown semantic op {op!r}")
        return out, [], {"level": level, **prov}
    raise ValueError(f"perturbation: unknown level {level!r}; expected control, physics or semantic")


def run_pair(src: FailureSource, scenario: str, seed: int, variant: str) -> tuple[Episode, Episode]:
    """Nominal and injected episodes of one task instance (same seed, so the same initial state)."""
    rng = np.random.default_rng([seed, 0xFA11])
    src.reset(scenario, seed, variant)
    nominal = src.execute(src.scripted_keyframes())
    specs = src.scenario_info(scenario)["perturbations"]
    src.reset(scenario, seed, variant)
    kfs, events, prov = src.scripted_keyframes(), [], {"level": "none"}
    if specs:
        spec = specs[int(rng.integers(len(specs)))]
        kfs, events, prov = apply_spec(spec, kfs, src.object_positions(), rng)
    injected = src.execute(kfs, events)
    injected.perturbation = prov
    nominal.perturbation = {"level": "none"}
    return nominal, injected
