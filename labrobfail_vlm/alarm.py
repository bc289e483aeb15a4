"""A failure alarm with a false-alarm bound: a running failure score over a trajectory's keyframes and a threshold
calibrated on successful trajectories only (split conformal prediction, as FIPER calibrates on successes).

The score of a trajectory at keyframe k is whatever the monitor gives for the trajectory seen so far (the model's
P(failure) on the prefix grid of keyframes 1..k, for one); the alarm fires at the first k whose score exceeds the
threshold. A success's nonconformity is its largest score over all its keyframes: the alarm fires on it somewhere
exactly when that maximum exceeds the threshold. With n calibration successes, the threshold is the
ceil((n + 1)(1 - alpha))-th smallest of their maxima (the order statistic; no interpolation), so that for a new
success exchangeable with them

    P(the alarm fires on it) <= alpha,

a finite-sample bound that holds for any score and any n, on average over calibration draws (Vovk et al.; Angelopoulos
and Bates, "A Gentle Introduction to Conformal Prediction", 2021). When (n + 1)(1 - alpha) > n there are too few
successes for the bound: the threshold is +inf and the alarm never fires (say so, and calibrate on more).

What it does not promise: anything on a success that is not exchangeable with the calibration set (a new scene, a
new policy, another camera: recalibrate there), any detection rate or latency on failures (those are measured),
nor a per-keyframe rate: the bound is per trajectory.

Several monitors (the VLM and a detector on the robot's own signals, as Sentinel pairs a cheap statistical
detector with a VLM) share one bound through `AnyAlarm`: each is calibrated at alpha / m on the same successes and
the pair fires at the first keyframe either fires, so by the union bound P(it fires on a new success) <= alpha
(Bonferroni; conservative where the monitors fire on the same successes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np


def trajectory_score(scores: Sequence[float]) -> float:
    """A success's nonconformity: its largest running score (the alarm fires on it iff this exceeds the threshold)."""
    if len(scores) == 0:
        raise ValueError("alarm: a trajectory needs at least one keyframe score")
    return float(np.max(np.asarray(scores, np.float64)))


def conformal_threshold(success_maxima: Sequence[float], alpha: float) -> float:
    """The split-conformal threshold: the ceil((n+1)(1-alpha))-th smallest calibration maximum, +inf when n is too
    small for alpha. The alarm fires where a score is strictly above it."""
    if not 0 < alpha < 1:
        raise ValueError(f"alarm: alpha must be in (0, 1), got {alpha!r}")
    s = np.sort(np.asarray(success_maxima, np.float64))
    if s.ndim != 1 or not np.all(np.isfinite(s)):
        raise ValueError("alarm: calibration scores must be a list of finite numbers")
    n = len(s)
    rank = math.ceil((n + 1) * (1 - alpha))
    return math.inf if rank > n else float(s[rank - 1])


def min_calibration(alpha: float) -> int:
    """The fewest calibration successes for which the threshold is finite at this alpha."""
    return math.ceil((1 - alpha) / alpha)


def false_alarm_pvalue(n_calibration: int, alpha: float, false_alarms: int, successes: int, monitors: int = 1) -> float:
    """How surprising `false_alarms` of `successes` new successes are if the guarantee holds: an upper bound on
    P(at least that many) for an alarm set at alpha on `n_calibration` exchangeable successes.

    One monitor: conditional on the calibration draw, the rate at which a new success raises the alarm is
    Beta(n + 1 - r, r) (r: the threshold's rank, continuous scores), so the count over the new successes is
    beta-binomial, exact, with the calibration's luck and the test's both in it; ties among scores only lower the
    rate. m monitors each set at alpha / m (AnyAlarm): the pair's count is at most the sum of theirs, and the sum
    reaches k only if monitor 1 reaches j or the others reach k - j + 1, so P <= min over j of the two tails, for any
    dependence between the monitors (conservative). A small value (under 0.05) says the new successes are not
    exchangeable with the calibration ones (a new scene, for one), not that the bound is wrong; a large one says
    the count is what the bound allows, also when it reads above alpha."""
    from scipy.stats import betabinom

    if not 0 <= false_alarms <= successes or n_calibration < 0 or monitors < 1:
        got = f"{false_alarms}, {successes}, {n_calibration}, {monitors}"
        raise ValueError(f"alarm: need 0 <= false alarms <= successes, n >= 0 and monitors >= 1 (got {got})")
    rank = math.ceil((n_calibration + 1) * (1 - alpha / monitors))
    if rank > n_calibration:  # every threshold is +inf: the alarm never fires
        return 1.0 if false_alarms == 0 else 0.0
    tail = betabinom.sf(np.arange(-1, successes + 1), successes, n_calibration + 1 - rank, rank)  # P(X >= i)

    def bound(k: int, m: int) -> float:  # an upper bound on P(m monitors' counts sum to at least k)
        if k <= 0:
            return 1.0
        if m == 1:
            return float(tail[min(k, successes + 1)])
        return min(1.0, *(float(tail[min(j, successes + 1)]) + bound(k - j + 1, m - 1) for j in range(1, k + 1)))

    return bound(false_alarms, monitors)


def first_alarm(scores: Sequence[float], threshold: float) -> int | None:
    """0-based keyframe of the first score above the threshold, or None."""
    hits = np.flatnonzero(np.asarray(scores, np.float64) > threshold)
    return int(hits[0]) if len(hits) else None


@dataclass(frozen=True)
class Alarm:
    """A calibrated alarm: `fires(scores)` gives the keyframe it fires at on a running trajectory, or None."""

    alpha: float
    threshold: float
    n_calibration: int

    @classmethod
    def calibrate(cls, success_scores: Sequence[Sequence[float]], alpha: float) -> "Alarm":
        """From the per-keyframe scores of successful calibration trajectories only."""
        maxima = [trajectory_score(s) for s in success_scores]
        return cls(float(alpha), conformal_threshold(maxima, alpha), len(maxima))

    def fires(self, scores: Sequence[float]) -> int | None:
        return first_alarm(scores, self.threshold)

    def to_dict(self) -> dict[str, float | int | None]:
        return {
            "alpha": self.alpha,
            "threshold": None if math.isinf(self.threshold) else self.threshold,
            "n_calibration": self.n_calibration,
        }


@dataclass(frozen=True)
class AnyAlarm:
    """m monitors' alarms, each calibrated at alpha / m: `fires(per_monitor_scores)` gives the first keyframe at which
    any of them fires, or None. With one monitor it is that monitor's Alarm at alpha."""

    alarms: tuple[Alarm, ...]

    @classmethod
    def calibrate(cls, success_scores: Sequence[Sequence[Sequence[float]]], alpha: float) -> "AnyAlarm":
        """`success_scores[i]`: monitor i's per-keyframe scores of the calibration successes (the same successes)."""
        if not success_scores or len({len(s) for s in success_scores}) != 1:
            raise ValueError("alarm: every monitor needs the scores of the same calibration successes")
        return cls(tuple(Alarm.calibrate(s, alpha / len(success_scores)) for s in success_scores))

    def fires(self, scores: Sequence[Sequence[float]]) -> int | None:
        hits = [f for a, s in zip(self.alarms, scores, strict=True) if (f := a.fires(s)) is not None]
        return min(hits) if hits else None

    def to_dict(self) -> dict[str, float | int | None | list[float | None]]:
        if len(self.alarms) == 1:
            return self.alarms[0].to_dict()
        ths = [a.to_dict()["threshold"] for a in self.alarms]
        n = self.alarms[0].n_calibration
        return {"alpha": sum(a.alpha for a in self.alarms), "thresholds": ths, "n_calibration": n}
