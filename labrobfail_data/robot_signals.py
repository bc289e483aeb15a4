"""What the online bench needs beside the grid, per grid frame of a trajectory, read from the shard's state trace:
when each frame was taken (sim seconds), when an irreversible event happened, and the robot's own signals.

The robot's signals are what a robot stack knows without a camera: proprioception (hand position, finger opening,
the gripper command sent) and the commanded keyframe (target position and gripper). They feed the online bench's
non-VLM baseline (labrobfail_vlm/bench/robot_baseline.py), in SAFE's manner of a small classifier on the robot's
own features. Nothing here reads an object's state: that is the labeler's (and the ceiling's) privilege.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from sim_backends.labeler import irreversible_sample

# the features of one grid frame, in order (robot_baseline.py adds the running maxima and the frame's position)
SIGNALS = (
    "ee_x",
    "ee_y",
    "ee_z",
    "width",
    "grip_cmd",
    "target_x",
    "target_y",
    "target_z",
    "target_gripper",
    "tracking_error",  # hand to commanded position at the frame (m)
    "segment_error_max",  # the largest hand-to-target distance over the keyframe's samples (m)
    "closed_width",  # the finger opening while the gripper is commanded closed (0 when open): an empty grasp closes
)


def _seconds(trace: dict[str, Any], j: int) -> float:
    return round(float(trace["t"][j]) - float(trace["t"][0]), 4)


def frame_times(trace: dict[str, Any], picks: list[int]) -> list[float]:
    """The sim time (s since the trace began) at which each grid frame's images were taken: its keyframe's end."""
    ends = trace["kf_end"]
    return [_seconds(trace, ends[min(p, len(ends) - 1)]) for p in picks]


def irreversible(trace: dict[str, Any], meta: dict[str, Any]) -> dict[str, Any]:
    """The first irreversible event's time and kind (None, None when there is none)."""
    hit = irreversible_sample(trace, meta)
    return (
        {"irreversible_s": None, "irreversible_event": None}
        if hit is None
        else {
            "irreversible_s": _seconds(trace, hit[0]),
            "irreversible_event": hit[1],
        }
    )


def robot_signals(trace: dict[str, Any], keyframes_json: str, picks: list[int]) -> list[list[float]]:
    """Per grid frame, the SIGNALS at its keyframe's end (rounded to 0.1 mm: the file stays small)."""
    kfs = json.loads(keyframes_json)
    ends = trace["kf_end"]
    ee = np.asarray(trace["ee_pos"], float)
    out = []
    for p in picks:
        p = min(p, len(ends) - 1, len(kfs) - 1)
        j, j0 = ends[p], (ends[p - 1] + 1 if p > 0 else 0)
        target = np.asarray(kfs[p]["pos"], float)
        seg = np.linalg.norm(ee[j0 : j + 1] - target, axis=1)
        grip = float(trace["grip_cmd"][j])
        row = [
            *ee[j],
            float(trace["width"][j]),
            grip,
            *target,
            float(kfs[p]["gripper"]),
            float(np.linalg.norm(ee[j] - target)),
            float(seg.max()),
            float(trace["width"][j]) * grip,
        ]
        out.append([round(float(x), 4) for x in row])
    return out
