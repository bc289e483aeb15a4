"""Which of the online bench's alarms to report, chosen on the calibration split alone.

The online bench (online.py) scores several alarms side by side: the model, the robot-signal MLP per grid frame and
at every trace sample, and their pairs at several shares of alpha. Picking the row to report by its test figures
would be choosing on test. Here the choice reads the calibration split only, by cross-fitting: its trajectories are
cut into `folds` folds by pair (a success and its failure twin always in one fold, the fold drawn from a digest of
the pair's name, so the same split gives the same folds); each fold is scored by the alarm calibrated on the other
folds' successes, exactly as the bench calibrates on one split and scores another (marginal or training-conditional,
as the bench's `delta`). Pooled over the folds, that gives each candidate a false-alarm rate on successes it was not
calibrated on, a detection rate, a latency and the spills and falls caught before they happen, without a test
trajectory.

The rule (written before any figure was read, 7 Dec): at alpha 0.05, the candidate that meets the most of the alarm
issue's four targets there (false alarms <= 5 %, detection >= 80 %, median latency <= 1 grid frame after the onset,
>= 60 % of spills and falls caught before the event), then the higher detection rate, then the larger share of
spills and falls caught before, then the first in the bench's order. The bench reports the chosen row's test figures
beside every other row; the choice cannot see them.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from labrobfail_vlm.bench.online_alarm import fire, summarise

ALPHA = 0.05
FOLDS = 5
GRAVE = ("spill", "fall")  # the "spills and falls"


@dataclass(frozen=True)
class Candidate:
    """One alarm as the bench calibrates it: each monitor's running scores per calibration trajectory, the sim time
    of each score for monitors checked at the trace's rate (None: per grid frame), and the monitors' shares of alpha."""

    cal: Sequence[Sequence[Sequence[float]]]
    axes: Sequence[np.ndarray] | None = None
    shares: Sequence[float] | None = None


def fold_of(group: str, folds: int) -> int:
    """The fold of a pair, from a digest of its name (not Python's salted hash: the same every run)."""
    return int.from_bytes(hashlib.blake2b(group.encode(), digest_size=8).digest(), "big") % folds


def crossfit(
    c: Candidate,
    trajs: Sequence[dict[str, Any]],
    alpha: float = ALPHA,
    folds: int = FOLDS,
    delta: float | None = None,
) -> dict[str, Any]:
    """The candidate's figures on `trajs` (the calibration split), each fold scored by the alarm calibrated on the
    other folds' successes (`delta`: the bench's, None: marginal); pooled as online_alarm.summarise reports a scored
    split."""
    fold = [fold_of(str(t.get("group", t["trajectory"])), folds) for t in trajs]
    when: list[tuple[int | None, float | None]] = []
    scored: list[dict[str, Any]] = []
    for f in range(folds):
        rest = [i for i, x in enumerate(fold) if x != f]
        held = [i for i, x in enumerate(fold) if x == f]
        if not held:
            continue
        pick = lambda seq, idx: [seq[i] for i in idx]  # noqa: E731
        axes = None if c.axes is None else pick(c.axes, held)
        cal = [pick(m, rest) for m in c.cal]
        held_m = [pick(m, held) for m in c.cal]
        _, w = fire(cal, pick(trajs, rest), held_m, pick(trajs, held), alpha, axes, c.shares, delta)
        when += w
        scored += pick(trajs, held)
    return summarise(when, scored)


def spills_and_falls(row: dict[str, Any]) -> tuple[int, int]:
    """(caught before the event, of) over the spills and falls of a row's tally per kind of event."""
    tally = row.get("caught_before_by_event") or {}
    return sum(tally.get(k, [0, 0])[0] for k in GRAVE), sum(tally.get(k, [0, 0])[1] for k in GRAVE)


def targets_met(row: dict[str, Any], alpha: float = ALPHA) -> list[str]:
    """Which of the issue's four targets a row meets (by its point figures)."""
    early, of = spills_and_falls(row)
    checks = {
        "false alarms": row.get("false_alarm_rate") is not None and row["false_alarm_rate"] <= alpha,
        "detection": (row.get("detection_rate") or 0.0) >= 0.8,
        "latency": row.get("latency_frames_median") is not None and row["latency_frames_median"] <= 1,
        "spills and falls": of > 0 and early / of >= 0.6,
    }
    return [name for name, ok in checks.items() if ok]


def choose(
    cands: dict[str, Candidate], trajs: Sequence[dict[str, Any]], folds: int = FOLDS, delta: float | None = None
) -> dict[str, Any]:
    """The cross-fitted figures of every candidate on the calibration split, each calibrated as the bench calibrates
    (`delta`), and the one the rule picks."""
    rows = {name: crossfit(c, trajs, ALPHA, folds, delta) for name, c in cands.items()}
    met = {name: targets_met(r) for name, r in rows.items()}

    def rank(name: str) -> tuple[int, float, float]:
        early, of = spills_and_falls(rows[name])
        return len(met[name]), rows[name]["detection_rate"] or 0.0, early / of if of else 0.0

    chosen = max(rows, key=rank) if rows else None  # max keeps the first of equals: the bench's order
    keep = ("false_alarm_rate", "successes", "detection_rate", "failures", "latency_frames_median")
    return {
        "alpha": ALPHA,
        "folds": folds,
        "chosen": chosen,
        "candidates": {
            n: {k: r.get(k) for k in keep} | {"spills_and_falls": list(spills_and_falls(r)), "targets_met": met[n]}
            for n, r in rows.items()
        },
    }
