"""Physics-level perturbations Phi_phy (paper Eq. 2), backend-agnostic.

psi~ = psi (1 + delta), delta ~ U(-alpha, alpha): both signs, as the paper writes it, with alpha in [0, 1)
per parameter in the task configs (`alpha: a`). An event names the parameter, the body it applies to
and the keyframe boundary at which the backend applies it; the backend knows how to set e.g. `friction`
on its own engine. A draw that causes no failure yields a labelled success (the labeler decides).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any, Sequence

import numpy as np

from sim_backends.types import Keyframe

PHYSICS_PARAMS = ("friction", "mass", "grip_force", "liquid_viscosity", "liquid_mass", "liquid_friction")


@dataclass(frozen=True)
class PhysicsEvent:
    param: str
    target: str
    scale: float
    at_keyframe: int  # applied when the controller starts moving towards this keyframe

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def events_from_record(perturbation: dict[str, Any]) -> list[PhysicsEvent]:
    """The events of a shard's `perturbation` record (what `sample_events` wrote: `{"level": "physics",
    "events": [...]}`; older shards hold one event's fields at the top level); none for other levels."""
    if perturbation.get("level") != "physics":
        return []
    evs = perturbation.get("events") or [perturbation]
    names = [f.name for f in fields(PhysicsEvent)]
    bad = next((e for e in evs if any(n not in e for n in names)), None)
    if bad is not None:
        raise ValueError(f"physics perturbation record lacks {[n for n in names if n not in bad]}: {bad}")
    return [PhysicsEvent(str(e["param"]), str(e["target"]), float(e["scale"]), int(e["at_keyframe"])) for e in evs]


def alpha_of(p: dict[str, Any]) -> float:
    """The half-width alpha of the paper's U(-alpha, alpha) for one parameter spec."""
    if "alpha" not in p:
        hint = " (one-sided `delta` ranges were replaced by the paper's alpha)" if "delta" in p else ""
        raise ValueError(f"physics perturbation of {p.get('param')!r} needs alpha{hint}")
    a = float(p["alpha"])
    if not 0.0 <= a < 1.0:
        raise ValueError(f"physics perturbation of {p.get('param')!r}: alpha must be in [0, 1), got {a}")
    return a


def sample_events(
    kfs: Sequence[Keyframe], spec: dict[str, Any], rng: np.random.Generator
) -> tuple[list[PhysicsEvent], dict]:
    """One or several parameters (`params: [{param, target, alpha}, ...]`) changed at one keyframe."""
    params = spec.get("params") or [spec]
    events, deltas = [], []
    at = None
    for prm in params:
        ev, prov = sample_event(kfs, prm["param"], prm["target"], spec["at"], alpha_of(prm), rng, at)
        at = ev.at_keyframe  # every parameter changes at the same moment
        events.append(ev)
        deltas.append(prov)
    return events, {"op": "physics", "events": deltas}


def sample_event(
    kfs: Sequence[Keyframe],
    param: str,
    target: str,
    at: Sequence[str],
    alpha: float,
    rng: np.random.Generator,
    at_index: int | None = None,
) -> tuple[PhysicsEvent, dict]:
    if param not in PHYSICS_PARAMS:
        raise ValueError(
            f"physics perturbation: unknown parameter {param!r}; expected one of {', '.join(PHYSICS_PARAMS)}"
        )
    names = [k.name for k in kfs]
    where = [names.index(a) for a in at if a in names]
    if not where:
        raise ValueError(f"physics perturbation names keyframes {list(at)} that the task does not have")
    d = float(rng.uniform(-alpha, alpha))
    ev = PhysicsEvent(param, target, 1.0 + d, int(rng.choice(where)) if at_index is None else at_index)
    return ev, {"op": "physics", **ev.to_dict(), "delta": round(d, 5), "alpha": alpha}
