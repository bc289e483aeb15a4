"""Semantic-level perturbations Phi_sem, backend-agnostic.

A permutation pi of the step (segment) indices models sequence reversal and
step omission; a mapping M(o_i) substitutes the interaction target of a step
(e.g. the wrong beaker, the wrong shelf).
"""

from __future__ import annotations

import dataclasses
from typing import Mapping, Sequence

import numpy as np

from sim_backends.types import Keyframe


def _segments(kfs: Sequence[Keyframe]) -> dict[int, list[Keyframe]]:
    out: dict[int, list[Keyframe]] = {}
    for k in kfs:
        out.setdefault(k.segment, []).append(k)
    return out


def _check(segs: dict[int, list[Keyframe]], wanted: Sequence[int]) -> None:
    missing = [s for s in wanted if s not in segs]
    if missing:
        raise ValueError(f"semantic perturbation names steps {missing} that the task does not have")


def permute(kfs: Sequence[Keyframe], a: int, b: int) -> tuple[list[Keyframe], dict]:
    """Swap steps a and b (sequence reversal)."""
    segs = _segments(kfs)
    _check(segs, [a, b])
    order = list(segs)
    ia, ib = order.index(a), order.index(b)
    order[ia], order[ib] = order[ib], order[ia]
    return [k for s in order for k in segs[s]], {"op": "permute", "swap": [a, b]}


def omit(kfs: Sequence[Keyframe], step: int) -> tuple[list[Keyframe], dict]:
    """Drop one step (step omission)."""
    segs = _segments(kfs)
    _check(segs, [step])
    return [k for k in kfs if k.segment != step], {"op": "omit", "step": step}


def substitute_target(
    kfs: Sequence[Keyframe],
    step: int,
    new_target: str,
    positions: Mapping[str, Sequence[float]],
    rng: np.random.Generator | None = None,
) -> tuple[list[Keyframe], dict]:
    """M(o_i): the keyframes of `step` aimed at o_i are shifted to aim at `new_target` instead."""
    segs = _segments(kfs)
    _check(segs, [step])
    old = segs[step][-1].target
    if old not in positions or new_target not in positions:
        raise ValueError(f"target substitution: unknown object {old if old not in positions else new_target!r}")
    shift = np.asarray(positions[new_target], float) - np.asarray(positions[old], float)
    shift[2] = 0.0  # heights stay those of the plan: only where the arm goes changes
    out = []
    for k in kfs:
        if k.segment == step and k.target == old:
            k = dataclasses.replace(k, pos=tuple(float(v) for v in np.asarray(k.pos) + shift), target=new_target)
        out.append(k)
    return out, {"op": "substitute_target", "step": step, "from": old, "to": new_target}
