"""Dataset splits: seen 8:1:1 train/val/test grouped by initial state; each held-out variant is a split of its own.

A group is a success/failure pair (same scenario, seed and variant, so the same initial
state): both trajectories land in the same split, so no test grid has a training twin.
Groups are ordered by a seeded hash and cut at 80 % and 90 %, which is deterministic and
exact up to one group.
"""

from __future__ import annotations

import hashlib
from typing import Iterable

from labrobfail_vlm.taxonomy import HELD_OUT_SPLITS, REPLAY_SPLITS, SCENE_VARIANTS, SEEN_SPLITS

__all__ = ["HELD_OUT_SPLITS", "SCENE_VARIANTS", "SEEN_SPLITS", "assign"]


def _key(group: str, seed: int) -> str:
    return hashlib.sha256(f"{seed}:{group}".encode()).hexdigest()


def assign(
    groups: Iterable[tuple[str, str]], seed: int = 0, ratios: tuple[float, float, float] = (0.8, 0.1, 0.1)
) -> dict[str, str]:
    """Map each (group, variant) to a split name."""
    out: dict[str, str] = {}
    seen: list[str] = []
    for g, variant in dict.fromkeys(groups):
        if variant in HELD_OUT_SPLITS or variant in REPLAY_SPLITS:  # named as its variant: val_*, test_*, replay_*
            out[g] = variant
        elif variant == SCENE_VARIANTS[0]:  # "seen"
            seen.append(g)
        else:
            raise ValueError(f"split: unknown variant {variant!r} in group {g!r}")
    seen.sort(key=lambda g: _key(g, seed))
    n = len(seen)
    a = round(n * ratios[0])
    b = a + round(n * ratios[1])
    for i, g in enumerate(seen):
        out[g] = "train" if i < a else "val" if i < b else "test"
    return out
