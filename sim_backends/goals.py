"""Task goals evaluated on a recorded state trace (backend-agnostic).

Each goal kind is a small predicate over trace columns; a task succeeds when
all its goals hold. The labeler also uses these to find which goal failed.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from sim_backends.schema import MOVABLE, Trace

Meta = dict[str, Any]

UPRIGHT_TILT = 0.35  # rad; beyond this a vessel counts as tipped over
OFF_BENCH = -0.1  # m below the bench top: knocked off the bench


def tilt(quat) -> float:
    """Angle between a body's z axis and the world z axis."""
    x, y, _, _ = quat
    zz = 1 - 2 * (x * x + y * y)
    return math.acos(max(-1.0, min(1.0, zz)))


def final(trace: Trace, col: str):
    return trace[col][-1]


def place_xy(meta: Meta, name: str) -> np.ndarray:
    return np.asarray(meta["places"][name][:2], float)


def _at(trace: Trace, meta: Meta, g: dict) -> bool:
    pos = np.asarray(final(trace, f"{g['object']}.pos"))
    return float(np.linalg.norm(pos[:2] - place_xy(meta, g["xy"]))) <= g["tol"] and pos[2] > meta["bench_top"] - 0.05


def _upright(trace: Trace, meta: Meta, g: dict) -> bool:
    return tilt(final(trace, f"{g['object']}.quat")) < UPRIGHT_TILT


def _released(trace: Trace, meta: Meta, g: dict) -> bool:
    return final(trace, f"{g['object']}.contacts") == 0


def _held(trace: Trace, meta: Meta, g: dict) -> bool:
    return final(trace, f"{g['object']}.contacts") >= 1


def bottom_z(trace: Trace, meta: Meta, obj: str, i: int) -> float:
    """z of the lower end of a rod-like object at sample i."""
    half = meta["objects"][obj]["dims"]["length"] / 2
    q = trace[f"{obj}.quat"][i]
    x, y, z, w = q
    axis_z = 1 - 2 * (x * x + y * y)
    return trace[f"{obj}.pos"][i][2] - half * abs(axis_z)


def _below(trace: Trace, meta: Meta, g: dict) -> bool:
    return bottom_z(trace, meta, g["object"], -1) < g["z"]


def _button(trace: Trace, meta: Meta, g: dict) -> bool:
    return max(trace[f"{g['object']}.q"]) >= g["min_travel"]


def _door(trace: Trace, meta: Meta, g: dict) -> bool:
    q = final(trace, f"{g['object']}.q")
    return (q >= g["min"]) if "min" in g else (q <= g["max"])


def _liquid(trace: Trace, meta: Meta, g: dict) -> bool:
    total = meta["liquid_total"].get(g["source"], 0)
    return total > 0 and final(trace, f"liquid.{g['into']}") >= g["min_fraction"] * total


def rod_in_vessel(trace: Trace, meta: Meta, rod: str, vessel: str, i: int) -> bool:
    v = meta["objects"][vessel]
    vp = np.asarray(trace[f"{vessel}.pos"][i])
    rp = np.asarray(trace[f"{rod}.pos"][i])
    return (
        float(np.linalg.norm(rp[:2] - vp[:2])) < v["dims"]["radius"]
        and bottom_z(trace, meta, rod, i) < vp[2] + v["dims"]["height"] - 0.01
    )


def stir_samples(trace: Trace, meta: Meta) -> list[int]:
    seg = [s for s in meta["steps"] if s["action"] == "stir"]
    if not seg:
        return []
    names = set(seg[0]["keyframes"])
    idx = [i for i, n in enumerate(meta["executed"]) if n in names]
    return [j for j, k in enumerate(trace["kf"]) if k in idx]


def _stirred(trace: Trace, meta: Meta, g: dict) -> bool:
    js = stir_samples(trace, meta)
    if not js:
        return False
    ok = sum(rod_in_vessel(trace, meta, g["object"], g["vessel"], j) for j in js)
    return ok >= g["min_fraction"] * len(js)


def _still(trace: Trace, meta: Meta, g: dict) -> bool:
    home = np.asarray(meta["objects"][g["object"]]["home"][:2])
    pos = np.asarray(final(trace, f"{g['object']}.pos"))
    return (
        float(np.linalg.norm(pos[:2] - home)) <= g["tol"] and tilt(final(trace, f"{g['object']}.quat")) < UPRIGHT_TILT
    )


GOALS: dict[str, Callable[[Trace, Meta, dict], bool]] = {
    "at": _at,
    "upright": _upright,
    "released": _released,
    "held": _held,
    "below": _below,
    "button": _button,
    "door": _door,
    "liquid": _liquid,
    "stirred": _stirred,
    "still": _still,
}


def failed_goals(trace: Trace, meta: Meta) -> list[dict]:
    return [g for g in meta["goals"] if not GOALS[g["kind"]](trace, meta, g)]


FALLEN_TILT = 1.0  # rad; a vessel lying on its side has fallen over


def object_fell(trace: Trace, meta: Meta) -> bool:
    """An object ended off the bench or lying on its side (the manual-operation case of Q6)."""
    for name, o in meta["objects"].items():
        if o["kind"] not in MOVABLE or f"{name}.pos" not in trace:
            continue
        if trace[f"{name}.pos"][-1][2] < meta["bench_top"] + OFF_BENCH:
            return True
        if o["kind"] == "vessel" and tilt(trace[f"{name}.quat"][-1]) > FALLEN_TILT:
            return True
    return False
