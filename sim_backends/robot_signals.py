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
from sim_backends.schema import image_samples

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
    """The sim time (s since the trace began) at which each grid frame's images were taken (its keyframe's end, or
    the settled state for a last keyframe drawn again: `image_samples`)."""
    ends = image_samples(trace)
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


def dense_table(trace: dict[str, Any], keyframes_json: str) -> np.ndarray:
    """One row per trace sample (the trace's rate, 40 Hz for PyBullet): its sim time (s since the trace began), the
    commanded keyframe it belongs to, the SIGNALS then: what a monitor checked at the robot's own rate sees
    (labrobfail_vlm/bench/robot_baseline.py DENSE_FILE). A sample belongs to the keyframe whose segment it ends or
    lies in (kf_end[p - 1] < j <= kf_end[p]; samples past the last keyframe's end to the last); `segment_error_max`
    is the running maximum over the keyframe's samples so far, so every row reads only the past."""
    kfs = json.loads(keyframes_json)
    ends = np.asarray(trace["kf_end"], int)
    ee = np.asarray(trace["ee_pos"], float)
    n = len(ee)
    p = np.minimum(np.searchsorted(ends, np.arange(n)), min(len(ends), len(kfs)) - 1)
    target = np.asarray([k["pos"] for k in kfs], float)[p]
    err = np.linalg.norm(ee - target, axis=1)
    # a running maximum that restarts at each keyframe's first sample (p never decreases: one run per keyframe)
    seg = np.concatenate([np.maximum.accumulate(s) for s in np.split(err, np.flatnonzero(np.diff(p)) + 1)])
    width = np.asarray(trace["width"], float)
    grip = np.asarray(trace["grip_cmd"], float)
    gripper = np.asarray([float(k["gripper"]) for k in kfs])[p]
    t = np.asarray(trace["t"], float)
    return np.column_stack([t - t[0], p, ee, width, grip, target, gripper, err, seg, width * grip])


def robot_signals(
    trace: dict[str, Any], keyframes_json: str, picks: list[int], dense: np.ndarray | None = None
) -> list[list[float]]:
    """Per grid frame, the SIGNALS at the sample its images show (`image_samples`; rounded to 0.1 mm: the file stays
    small): the dense rows (`dense`: dense_table's, computed here when not given) at the frames' samples."""
    dense = (dense_table(trace, keyframes_json) if dense is None else dense)[:, 2:]
    ends = image_samples(trace)
    n_kf = len(json.loads(keyframes_json))
    rows = [dense[ends[min(p, len(ends) - 1, n_kf - 1)]] for p in picks]
    return [[round(float(x), 4) for x in row] for row in rows]
