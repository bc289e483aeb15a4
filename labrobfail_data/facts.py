"""Dense per-frame state facts: auxiliary training records that the simulator gives for free.

A Yes/No per grid says little about where to look; a from-scratch vision tower learns more from many small,
visible facts about single frames. For each grid frame k (the state its images show, the sample `image_samples`
gives: its keyframe's end) this reads the state trace and the task metadata, through the backend-neutral trace schema
(sim_backends/schema.py) and the goal predicates (sim_backends/goals.py), never the injected perturbation:

  lifted   "In frame k, is the <object> lifted above the bench?"        object z over its start + 3 cm
  goal     "In frame k, is the <object> at the <place>?" / "... upright?" / "... door closed (open)?" /
           "... has the liquid reached the <vessel>?" / "... has the <button> been pressed?"
           each task goal evaluated on the trace up to that frame

The facts become records `<trajectory>_A<i>` with the grid's preamble, so they pack into the trajectory's row
(labrobfail_vlm/train/packing.py) at a few tokens each. They go to the training split only
(`aux.per_trajectory` in configs/dataset.yaml); the benchmark never asks them.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from labrobfail_vlm import questions as Q
from sim_backends.goals import GOALS
from sim_backends.schema import image_samples, movables, trace_at

LIFT = 0.03  # m above the object's start height: lifted off the bench


def _goal_question(g: dict[str, Any], word) -> str | None:
    kind = g["kind"]
    if kind == "at":
        place = "its original position" if g["xy"] == g["object"] else f"the {word(g['xy'])}"
        return f"is the {word(g['object'])} at {place}?"
    if kind == "upright":
        return f"is the {word(g['object'])} upright?"
    if kind == "door":
        return f"is the door of the {word(g['object'])} {'open' if 'min' in g else 'closed'}?"
    if kind == "liquid":
        return f"has the liquid reached the {word(g['into'])}?"
    if kind == "button":
        return f"has the {word(g['object'])} been pressed?"
    return None  # released/held/below/stirred/still: not something one frame shows


def frame_facts(trace: dict[str, Any], meta: dict[str, Any], picks: list[int]) -> list[tuple[int, str, bool]]:
    """(1-based frame, question without the frame prefix, answer) for every fact of every grid frame."""
    labels = meta.get("labels", {})
    word = lambda role: labels.get(role, str(role).replace("_", " "))  # noqa: E731
    out: list[tuple[int, str, bool]] = []
    movable = movables(trace, meta)
    shots = image_samples(trace)
    for frame, kf in enumerate(picks, 1):
        j = shots[kf]
        for o in movable:
            z0 = meta["objects"][o]["home"][2]
            out.append((frame, f"is the {word(o)} lifted above the bench?", trace[f"{o}.pos"][j][2] > z0 + LIFT))
        upto = trace_at(trace, j)
        for g in meta["goals"]:
            q = _goal_question(g, word)
            if q is not None:
                out.append((frame, q, bool(GOALS[g["kind"]](upto, meta, g))))
    return out


def aux_records(
    traj: str, image: str, preamble: str, facts: list[tuple[int, str, bool]], n: int, rng: np.random.Generator
) -> list[dict[str, Any]]:
    """Up to n fact records, half Yes and half No where the facts allow (a constant answer teaches nothing)."""
    yes = [f for f in facts if f[2]]
    no = [f for f in facts if not f[2]]
    picked: list[tuple[int, str, bool]] = []
    for pool, want in ((yes, n // 2), (no, n - n // 2)):
        picked += [pool[i] for i in rng.permutation(len(pool))[:want]]
    rest = [f for f in facts if f not in picked]
    picked += [rest[i] for i in rng.permutation(len(rest))[: n - len(picked)]]
    return [
        {
            "id": Q.record_id(traj, f"{Q.AUX_PREFIX}{i}"),
            "image": image,
            "images": [image],
            "conversations": [
                {"from": "human", "value": f"<image>\n{preamble} In frame {frame}, {q} (Yes/No)"},
                {"from": "gpt", "value": "Yes" if ans else "No"},
            ],
        }
        for i, (frame, q, ans) in enumerate(sorted(picked))
    ]
