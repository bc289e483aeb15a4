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

That bound is on average over calibration draws: the rate an alarm set on one draw actually has is Beta(n + 1 - r,
r) (r: the threshold's rank), spread about alpha by about sqrt(alpha / n), so a marginal alarm runs above alpha on
new successes nearly as often as below (at alpha 0.05, on 36-47 % of draws for n from 20 to 500). Given `delta`, the
rank is raised to the smallest r whose Beta law puts at most delta above alpha (training-conditional validity, Vovk,
"Conditional validity of inductive conformal predictors", 2012): with probability at least 1 - delta over the
calibration draw, the alarm's rate on new exchangeable successes is at most alpha. It is the same order statistic at
a higher rank, and costs detection.

What it does not promise: anything on a success that is not exchangeable with the calibration set (a new scene, a
new policy, another camera: recalibrate there), any detection rate or latency on failures (those are measured),
nor a per-keyframe rate: the bound is per trajectory.

Several monitors (the VLM and a detector on the robot's own signals, as Sentinel pairs a cheap statistical
detector with a VLM) share one bound through `AnyAlarm`: monitor i is calibrated at alpha * share_i on the same
successes (the shares sum to 1: alpha / m each by default) and the pair fires at the first keyframe either fires, so
by the union bound P(it fires on a new success) <= sum_i alpha * share_i = alpha (Bonferroni, which holds for any
split fixed before the calibration draw; conservative where the monitors fire on the same successes).
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


def conformal_threshold(success_maxima: Sequence[float], alpha: float, delta: float | None = None) -> float:
    """The split-conformal threshold: the conformal_rank-th smallest calibration maximum, +inf when n is too small
    for alpha (and delta). The alarm fires where a score is strictly above it."""
    if not 0 < alpha < 1:
        raise ValueError(f"alarm: alpha must be in (0, 1), got {alpha!r}")
    s = np.sort(np.asarray(success_maxima, np.float64))
    if s.ndim != 1 or not np.all(np.isfinite(s)):
        raise ValueError("alarm: calibration scores must be a list of finite numbers")
    n = len(s)
    rank = conformal_rank(n, alpha, delta)
    return math.inf if rank > n else float(s[rank - 1])


def conformal_rank(n: int, alpha: float, delta: float | None = None) -> int:
    """The threshold's rank among n calibration maxima at alpha (over n: the threshold is +inf). One function for the
    threshold and its bound check, so that both read the same rank from the same float. None: ceil((n+1)(1-alpha)),
    the marginal bound; delta: the smallest rank r from that one up (so the marginal bound holds too) whose rate law
    Beta(n + 1 - r, r) puts at most delta above alpha."""
    rank = math.ceil((n + 1) * (1 - alpha))
    if delta is None:
        return rank
    if not 0 < delta < 1:
        raise ValueError(f"alarm: delta must be in (0, 1) or None, got {delta!r}")
    from scipy.stats import beta

    while rank <= n and beta.sf(alpha, n + 1 - rank, rank) > delta:
        rank += 1
    return rank


def min_calibration(alpha: float, delta: float | None = None) -> int:
    """The fewest calibration successes for which the threshold is finite at this alpha (and delta): from just under
    the closed forms ((1 - alpha) / alpha; with delta, also log(delta) / log(1 - alpha), where the top rank's law puts
    (1 - alpha)^n above alpha) up to the first n whose rank conformal_rank gives, so both read the same floats."""
    n = math.ceil((1 - alpha) / alpha)
    if delta is not None:
        n = max(n, math.floor(math.log(delta) / math.log(1 - alpha)))
    n = max(1, n - 1)
    while conformal_rank(n, alpha, delta) > n:
        n += 1
    return n


def monitor_alphas(alpha: float, monitors: int, shares: Sequence[float] | None = None) -> tuple[float, ...]:
    """Each monitor's level: alpha * shares[i] (shares positive, one per monitor, summing to 1), or alpha / m each
    when `shares` is None."""
    if shares is None:
        return (alpha / monitors,) * monitors
    out = tuple(float(x) for x in shares)
    if len(out) != monitors or not all(0 < x <= 1 for x in out) or abs(sum(out) - 1) > 1e-9:
        raise ValueError(f"alarm: shares must be {monitors} positive numbers that sum to 1, got {list(shares)!r}")
    return tuple(alpha * x for x in out)


def false_alarm_pvalue(
    n_calibration: int,
    alpha: float,
    false_alarms: int,
    successes: int,
    monitors: int = 1,
    alphas: Sequence[float] | None = None,
    deltas: Sequence[float | None] | None = None,
) -> float:
    """How surprising `false_alarms` of `successes` new successes are if the guarantee holds: an upper bound on
    P(at least that many) for an alarm set at alpha on `n_calibration` exchangeable successes.

    One monitor: conditional on the calibration draw, the rate at which a new success raises the alarm is
    Beta(n + 1 - r, r) (r: the threshold's rank, continuous scores), so the count over the new successes is
    beta-binomial, exact, with the calibration's luck and the test's both in it; ties among scores only lower the
    rate. m monitors, monitor i set at alphas[i] (AnyAlarm's levels, exactly as it set them; alpha / m each when
    None; `deltas`: their training-conditional deltas, which set r, None: marginal): the pair's count is at most
    the sum of theirs, and the sum reaches k only if monitor 1 reaches j or the others reach k - j + 1, so P <= min
    over j of the two tails, for any dependence between the monitors (conservative; a monitor that can never fire adds
    nothing). A small value (under 0.05) says the new successes are not exchangeable with the calibration ones (a new
    scene, for one), not that the bound is wrong; a large one says the count is what the bound allows, also when it
    reads above alpha.
    """
    from scipy.stats import betabinom

    if not 0 <= false_alarms <= successes or n_calibration < 0 or monitors < 1:
        got = f"{false_alarms}, {successes}, {n_calibration}, {monitors}"
        raise ValueError(f"alarm: need 0 <= false alarms <= successes, n >= 0 and monitors >= 1 (got {got})")
    levels = monitor_alphas(alpha, monitors) if alphas is None else tuple(alphas)
    ds = (None,) * monitors if deltas is None else tuple(deltas)
    if len(levels) != monitors or len(ds) != monitors:
        got = f"{list(levels)!r}, {list(ds)!r}"
        raise ValueError(f"alarm: {monitors} monitors need as many levels and deltas, got {got}")
    tails = []  # per monitor that can fire: P(its count >= i), i = -1..successes
    for level, d in zip(levels, ds):
        rank = conformal_rank(n_calibration, level, d)
        if rank <= n_calibration:  # otherwise its threshold is +inf: it never fires and adds nothing
            tails.append(betabinom.sf(np.arange(-1, successes + 1), successes, n_calibration + 1 - rank, rank))
    if not tails:  # every threshold is +inf: the alarm never fires
        return 1.0 if false_alarms == 0 else 0.0

    def bound(k: int, m: int) -> float:  # an upper bound on P(the last m monitors' counts sum to at least k)
        tail = tails[len(tails) - m]
        if k <= 0:
            return 1.0
        if m == 1:
            return float(tail[min(k, successes + 1)])
        return min(1.0, *(float(tail[min(j, successes + 1)]) + bound(k - j + 1, m - 1) for j in range(1, k + 1)))

    return bound(false_alarms, len(tails))


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
    delta: float | None = None

    @classmethod
    def calibrate(cls, success_scores: Sequence[Sequence[float]], alpha: float, delta: float | None = None) -> "Alarm":
        """From the per-keyframe scores of successful calibration trajectories only; `delta`: training-conditional
        (the rate is at most alpha with probability 1 - delta over the calibration draw), None: marginal."""
        maxima = [trajectory_score(s) for s in success_scores]
        return cls(float(alpha), conformal_threshold(maxima, alpha, delta), len(maxima), delta)

    def fires(self, scores: Sequence[float]) -> int | None:
        return first_alarm(scores, self.threshold)

    def to_dict(self) -> dict[str, float | int | None]:
        out: dict[str, float | int | None] = {
            "alpha": self.alpha,
            "threshold": None if math.isinf(self.threshold) else self.threshold,
            "n_calibration": self.n_calibration,
        }
        return out if self.delta is None else out | {"delta": self.delta}  # a marginal alarm's JSON as before


@dataclass(frozen=True)
class AnyAlarm:
    """m monitors' alarms, monitor i calibrated at alpha * shares[i] (alpha / m each by default): `fires(per_monitor_
    scores)` gives the first keyframe at which any of them fires, or None. With one monitor it is that monitor's Alarm
    at alpha."""

    alarms: tuple[Alarm, ...]

    @classmethod
    def calibrate(
        cls,
        success_scores: Sequence[Sequence[Sequence[float]]],
        alpha: float,
        shares: Sequence[float] | None = None,
        delta: float | None = None,
    ) -> "AnyAlarm":
        """`success_scores[i]`: monitor i's per-keyframe scores of the calibration successes (the same successes);
        `shares[i]`: its share of alpha (monitor_alphas) and, given `delta`, of delta (each monitor's rate is over
        its level with probability at most its share of delta, so the pair's is over alpha with at most delta)."""
        if not success_scores or len({len(s) for s in success_scores}) != 1:
            raise ValueError("alarm: every monitor needs the scores of the same calibration successes")
        levels = monitor_alphas(alpha, len(success_scores), shares)
        ds = (None,) * len(levels) if delta is None else monitor_alphas(delta, len(levels), shares)
        return cls(tuple(Alarm.calibrate(s, a, d) for s, a, d in zip(success_scores, levels, ds)))

    def fires(self, scores: Sequence[Sequence[float]]) -> int | None:
        hits = [f for a, s in zip(self.alarms, scores, strict=True) if (f := a.fires(s)) is not None]
        return min(hits) if hits else None

    def to_dict(self) -> dict[str, float | int | None | list[float | None]]:
        if len(self.alarms) == 1:
            return self.alarms[0].to_dict()
        ths = [a.to_dict()["threshold"] for a in self.alarms]
        n = self.alarms[0].n_calibration
        alphas = [a.alpha for a in self.alarms]  # exact: the bound check reads the ranks the thresholds were set at
        out = {"alpha": round(sum(alphas), 12), "thresholds": ths, "n_calibration": n, "alphas": alphas}
        deltas = [a.delta for a in self.alarms]
        return out if deltas[0] is None else out | {"deltas": deltas}
