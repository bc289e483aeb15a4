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


def apply_spec(
    spec: dict[str, Any], kfs: Sequence[Keyframe], positions: dict, rng: np.random.Generator
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
        evs, prov = physics.sample_events(kfs, spec, rng)
        return list(kfs), evs, {"level": level, **prov}
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


def run_nominal(src: FailureSource, scenario: str, seed: int, variant: str, then_draw: int | None = None) -> Episode:
    """The unperturbed plan from the seeded initial state. `then_draw`: the injected draw run next from the same
    state, which a source that reuses prefixes (`reuse_prefix`) then starts where the two plans part."""
    src.reset(scenario, seed, variant)
    then = None
    if then_draw is not None and src.reuse_prefix:
        kfs, events, _ = injected_plan(src, scenario, seed, then_draw)
        then = (kfs, events)
    ep = src.execute(src.scripted_keyframes(), then=then)
    ep.perturbation = {"level": "none"}
    return ep


def draw_spec(specs: Sequence[dict[str, Any]], rng: np.random.Generator) -> dict[str, Any]:
    """One perturbation of the scenario's list, with probability proportional to its `weight` (default 1)."""
    w = np.asarray([float(s.get("weight", 1.0)) for s in specs])
    return specs[int(rng.choice(len(specs), p=w / w.sum()))]


def perturbation_rng(seed: int, draw: int = 0) -> np.random.Generator:
    """The random stream that picks and parameterises the perturbation of the episode with this seed
    (`draw` > 0: a redraw). A policy that injects the dataset's failures draws from the same stream."""
    return np.random.default_rng([seed, 0xFA11] + ([draw] if draw else []))


def injected_plan(
    src: FailureSource, scenario: str, seed: int, draw: int = 0
) -> tuple[list[Keyframe], list[PhysicsEvent], dict]:
    """The keyframes, physics events and provenance of the injected episode with this seed and draw, for the
    scene `reset` built (the perturbation's stream is a function of the seed and draw alone)."""
    rng = perturbation_rng(seed, draw)
    specs = src.scenario_info(scenario)["perturbations"]
    if not specs:
        return src.scripted_keyframes(), [], {"level": "none"}
    return apply_spec(draw_spec(specs, rng), src.scripted_keyframes(), src.object_positions(), rng)


def run_injected(src: FailureSource, scenario: str, seed: int, variant: str, draw: int = 0) -> Episode:
    """The same initial state under one perturbation; `draw` > 0 draws another perturbation."""
    src.reset(scenario, seed, variant)
    kfs, events, prov = injected_plan(src, scenario, seed, draw)
    injected = src.execute(kfs, events)
    injected.perturbation = prov
    return injected


def run_pair(src: FailureSource, scenario: str, seed: int, variant: str) -> tuple[Episode, Episode]:
    """Nominal and injected episodes of one task instance (same seed, so the same initial state)."""
    return run_nominal(src, scenario, seed, variant), run_injected(src, scenario, seed, variant)
