"""A saved robot-signal monitor run live: the online bench's MLPs and calibrated thresholds (labrobfail_vlm/monitor.py)
read on the running episode's state trace, the robot's own signals only (sim_backends/robot_signals.py: hand,
fingers, gripper command, the commanded keyframes; no object's state, which is the labeler's privilege).

- The every-sample MLP reads each trace sample (40 Hz in PyBullet) with features of the past only, so its live score
  at a sample is the one the bench gives the same sample of the recorded episode (which stores the signals as
  float32: tests/test_monitor.py).
- The per-frame MLP reads the frames the supervisor's grid shows so far (`live_picks`), at k / F with F the grid's
  frames as laid out from the plan. Where a failure changes the episode's length, F differs from the recorded
  episode's count, and its score with it.

The alarm sounds where the bench's would: a member's score strictly above its threshold, a pair where either is.
The calibrated bound is on an episode's first alarm (no calibration success was corrected halfway): the VLM
supervisor acts on that one and then stands the monitor down (sim_backends/supervision/vlm.py).
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from labrobfail_vlm.monitor import RobotMonitor
from sim_backends.robot_signals import dense_table, robot_signals
from sim_backends.schema import image_samples
from sim_backends.source import FailureSource
from sim_backends.supervision.base import live_picks


class LiveMonitor:
    def __init__(self, monitor: RobotMonitor):
        self.monitor = monitor

    def check(self, src: FailureSource, nominal: list) -> dict[str, Any] | None:
        """Whether the alarm has sounded in the episode so far: None, or where first ({"member", "t_s": sim seconds
        since the trace began, "keyframe": the executed keyframe, "score", "threshold"})."""
        done = src.executed_so_far()
        if not done:
            return None
        trace = src.trace_so_far()
        keyframes = json.dumps([k.to_dict() for k in done])
        table = dense_table(trace, keyframes)
        found = [h for h in (self._dense(table), self._frames(trace, keyframes, done, nominal, table)) if h is not None]
        return min(found, key=lambda h: h["t_s"]) if found else None

    def _hit(self, member: str, t_s: float, keyframe: int, score: float) -> dict[str, Any]:
        return {
            "member": member,
            "t_s": round(float(t_s), 4),
            "keyframe": int(keyframe),
            "score": round(float(score), 6),
            "threshold": self.monitor.members[member][1],
        }

    def _dense(self, table: np.ndarray) -> dict[str, Any] | None:
        scores = self.monitor.dense_scores(table)
        i = self.monitor.sounds("dense", scores)
        return None if i is None or scores is None else self._hit("dense", table[i, 0], table[i, 1], scores[i])

    def _frames(
        self, trace: dict[str, Any], keyframes: str, done: list, nominal: list, table: np.ndarray
    ) -> dict[str, Any] | None:
        if "frame" not in self.monitor.members:
            return None
        units, picks = live_picks(done, nominal, self.monitor.max_frames)
        shown = [units[p] for p in picks if p < len(units)]
        scores = self.monitor.frame_scores(robot_signals(trace, keyframes, shown, table), len(picks))
        i = self.monitor.sounds("frame", scores)
        if i is None or scores is None:
            return None
        return self._hit("frame", table[image_samples(trace)[shown[i]], 0], shown[i], scores[i])
