"""Physics-level perturbations Phi_phy (paper Eq. 2), backend-agnostic.

psi~ = psi (1 + delta), delta ~ U(lo, hi) (the paper's U(-alpha, alpha) when
lo = -alpha, hi = alpha). An event names the parameter, the body it applies to
and the keyframe boundary at which the backend applies it; the backend knows
how to set e.g. `friction` on its own engine.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Sequence

import numpy as np

from sim_backends.types import Keyframe

PHYSICS_PARAMS = ("friction", "mass", "grip_force", "liquid_viscosity", "liquid_mass")


@dataclass(frozen=True)
class PhysicsEvent:
    param: str
    target: str
    scale: float
    at_keyframe: int  # applied when the controller starts moving towards this keyframe

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def sample_event(kfs: Sequence[Keyframe], param: str, target: str, at: Sequence[str], delta: Sequence[float],
                 rng: np.random.Generator) -> tuple[PhysicsEvent, dict]:
    if param not in PHYSICS_PARAMS:
        raise ValueError(f"physics perturbation: unknown parameter {param!r}; expected one of {', '.join(PHYSICS_PARAMS)}")
    lo, hi = float(delta[0]), float(delta[1])
    if not (-1.0 < lo <= hi):
        raise ValueError(f"physics perturbation: delta range {list(delta)} must satisfy -1 < lo <= hi")
    names = [k.name for k in kfs]
    where = [names.index(a) for a in at if a in names]
    if not where:
        raise ValueError(f"physics perturbation names keyframes {list(at)} that the task does not have")
    d = float(rng.uniform(lo, hi))
    ev = PhysicsEvent(param, target, 1.0 + d, int(rng.choice(where)))
    return ev, {"op": "physics", **ev.to_dict(), "delta": round(d, 5)}
