"""Running a calibrated alarm over scored trajectories, and what the online bench reports of when it sounded.

The alarm is calibrated on a calibration split's successes (labrobfail_vlm/alarm.py: split conformal, marginal or
training-conditional), then run on every scored trajectory; per alpha, a row gives the false-alarm rate on
successes with its bound check, the detection rate, the latency from the onset in grid frames and sim seconds and
the failures caught before an irreversible event (spill, fall, breakage, out of reach) with exact intervals. The
labeler on live state (`ceiling`) is the row no monitor can beat. online.py runs the bench; online_choice.py
cross-fits these same functions on the calibration split; online_page.py writes their tables.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from labrobfail_vlm.alarm import AnyAlarm, false_alarm_pvalue
from labrobfail_vlm.config import is_number

ALPHAS = (0.01, 0.05, 0.1, 0.2)


def alpha_key(alpha: object) -> str:
    """The key of `alpha` in a bench row (and a saved monitor's): its float's str, 0.05 -> "0.05"; a value that is
    no number as it reads (so that a lookup of it finds nothing)."""
    return str(float(alpha)) if is_number(alpha) else str(alpha)  # type: ignore[arg-type]


LABELER = "labeler on live state (ceiling)"


def alarm_rows(
    cal: Sequence[Sequence[Sequence[float]]],
    cal_trajs: Sequence[dict[str, Any]],
    ev: Sequence[Sequence[Sequence[float]]],
    ev_trajs: Sequence[dict],
    axes: Sequence[np.ndarray] | None = None,
    shares: Sequence[float] | None = None,
    delta: float | None = None,
) -> dict[str, Any]:
    """Per alpha: the calibrated threshold(s), false alarms on successes, detection and latency on failures.
    `cal`, `ev`: one or more monitors' running scores per trajectory; several share alpha (alarm.AnyAlarm).
    `axes`: per scored trajectory, the sim time of each score, for monitors checked at the trace's rate (None: one
    score per grid frame); latency in frames then counts to the first grid frame taken once the alarm sounded.
    `shares`: each monitor's share of alpha (alarm.monitor_alphas; equal when None). `delta`: training-conditional
    calibration (alarm.py; None: marginal)."""
    out: dict[str, Any] = {}
    for alpha in ALPHAS:
        alarm, when = fire(cal, cal_trajs, ev, ev_trajs, alpha, axes, shares, delta)
        row = out[alpha_key(alpha)] = alarm.to_dict() | summarise(when, ev_trajs)
        row["bound_p"] = bound_check(row)
    return out


def fire(
    cal: Sequence[Sequence[Sequence[float]]],
    cal_trajs: Sequence[dict[str, Any]],
    ev: Sequence[Sequence[Sequence[float]]],
    ev_trajs: Sequence[dict],
    alpha: float,
    axes: Sequence[np.ndarray] | None = None,
    shares: Sequence[float] | None = None,
    delta: float | None = None,
) -> tuple[AnyAlarm, list[tuple[int | None, float | None]]]:
    """The alarm calibrated at alpha (and delta) on `cal`'s successes, and per scored trajectory when it sounded
    (sounded())."""
    succ = [[s for s, t in zip(c, cal_trajs) if t["success"]] for c in cal]
    alarm = AnyAlarm.calibrate(succ, alpha, shares, delta)
    fired = [alarm.fires(s) for s in zip(*ev)]
    return alarm, [sounded(f, t, None if axes is None else axes[i]) for i, (f, t) in enumerate(zip(fired, ev_trajs))]


def summarise(when: Sequence[tuple[int | None, float | None]], ev_trajs: Sequence[dict]) -> dict[str, Any]:
    """False alarms on successes, detection, latency from the onset and the events caught before, from when the
    alarm sounded on each scored trajectory."""
    frames = [w[0] for w in when]
    ok = [f for f, t in zip(frames, ev_trajs) if t["success"]]
    lat = [f + 1 - int(t["frame"]) for f, t in zip(frames, ev_trajs) if not t["success"] and f is not None]
    fails = sum(not t["success"] for t in ev_trajs)
    alarms = sum(f is not None for f in ok)
    return {
        "false_alarm_rate": _share(alarms, len(ok)),
        "false_alarms": alarms,
        "successes": len(ok),
        "detection_rate": _share(len(lat), fails),
        "detected": len(lat),
        "failures": fails,
        "latency_frames_median": float(np.median(lat)) if lat else None,
        "latency_frames_p90": float(np.percentile(lat, 90)) if lat else None,
        "caught_by_onset": _share(sum(x <= 0 for x in lat), fails),
    } | timing([w[1] for w in when], ev_trajs)


def sounded(f: int | None, traj: dict[str, Any], axis: np.ndarray | None) -> tuple[int | None, float | None]:
    """An alarm that fired at score f: the grid frame (0-based) by whose images it has sounded, and its sim time
    (None without the dataset's frame times). At the trace's rate (`axis`), the frame is the first one taken at or
    after the alarm (one past the last, if it sounded after every frame)."""
    times = traj.get("frame_times_s")
    if f is None:
        return None, None
    if axis is None:
        return f, (float(times[f]) if times else None)
    t = round(float(axis[f]), 4)
    return int(np.searchsorted(times, t)), t


def on_axis(scores: Sequence[float], times: Sequence[float], axis: np.ndarray) -> np.ndarray:
    """A per-grid-frame score as it stands at each time of `axis`: the latest frame's score, -inf before the first
    frame (the same maximum, so the same calibration; it fires at its frame's time)."""
    idx = np.searchsorted(np.asarray(times, np.float64), axis, side="right") - 1
    return np.where(idx >= 0, np.asarray(scores, np.float64)[np.maximum(idx, 0)], -np.inf)


def count_of(row: dict[str, Any], rate_key: str, count_key: str, of: str) -> int | None:
    """A row's count (false alarms of successes, detections of failures): the JSON's own (from 7 Dec evening), or
    before that its rate, rounded to 4 digits, times n, which is exact only under n = 10,000 (None above)."""
    k, rate, n = row.get(count_key), row.get(rate_key), row.get(of)
    if k is None and rate is not None and n and n < 10_000:
        k = round(rate * n)
    return k


def bound_check(row: dict[str, Any]) -> float | None:
    """A row's false alarms against its bound (alarm.false_alarm_pvalue; for a pair of monitors, its union bound),
    from the row's own fields so that a bench JSON written before the check reads the same; None for a row without
    successes or one that never alarms (the majority class)."""
    k = count_of(row, "false_alarm_rate", "false_alarms", "successes")
    if not row.get("successes") or "n_calibration" not in row or k is None:
        return None
    m = len(row.get("thresholds", [None]))
    alphas = row.get("alphas")  # a pair's levels as its thresholds were set (a JSON from before pair_shares: halves)
    # None: marginal (every JSON before 7 Dec, afternoon)
    deltas = row.get("deltas", [row["delta"]] if "delta" in row else None)
    p = false_alarm_pvalue(int(row["n_calibration"]), float(row["alpha"]), k, int(row["successes"]), m, alphas, deltas)
    return float(f"{p:.3g}")


def timing(fired_s: Sequence[float | None], trajs: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Latency from the onset in sim seconds (`fired_s`: when each alarm sounded, None if never), and the share of the
    failures with an irreversible event (spill, fall, breakage, out of reach) whose alarm sounded before it. Empty
    for a dataset built before 29 Nov (no frame times, onsets or events)."""
    if not all(t.get("frame_times_s") and "irreversible_s" in t for t in trajs):
        return {}
    fails = [(s, t) for s, t in zip(fired_s, trajs) if not t["success"]]
    lat = [s - t["onset_s"] for s, t in fails if s is not None and t.get("onset_s") is not None]
    grave = [(s, t) for s, t in fails if t["irreversible_s"] is not None]
    return {
        "latency_s_median": round(float(np.median(lat)), 3) if lat else None,
        "latency_s_p90": round(float(np.percentile(lat, 90)), 3) if lat else None,
        **_before_irreversible([(s is not None and s < t["irreversible_s"], t) for s, t in grave]),
    }


def ceiling(trajs: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The labeler on live state: it alarms exactly at each failure's onset frame and never on a success."""
    fails = sum(not t["success"] for t in trajs)
    out = {
        "false_alarm_rate": 0.0,
        "detection_rate": 1.0 if fails else None,
        "latency_frames_median": 0.0,
        "latency_frames_p90": 0.0,
        "caught_by_onset": 1.0 if fails else None,
    }
    if all("irreversible_s" in t for t in trajs):  # it sounds at the onset itself: before the event unless they meet
        grave = [t for t in trajs if not t["success"] and t["irreversible_s"] is not None]
        early = [(t.get("onset_s") is not None and t["onset_s"] < t["irreversible_s"], t) for t in grave]
        out |= {"latency_s_median": 0.0, "latency_s_p90": 0.0, **_before_irreversible(early)}
    return out


def _before_irreversible(caught: list[tuple[bool, dict[str, Any]]]) -> dict[str, Any]:
    """Of the failures with an irreversible event (each with whether its alarm sounded before it): the share caught
    before, with its exact (Clopper-Pearson) 95 % interval, and per kind of event (spill, fall, breakage, out of
    reach: [caught, of]). A test split holds a handful of such events, and a share of 5 in 9 reads the same as 50 in
    90 without an interval; each is the failure of its own pair (a success twin has no event), so the failures are
    independent draws and a binomial interval needs no resampling by pair. The interval is given the calibrated
    threshold: it leaves out the calibration draw's own variation."""
    early, n = sum(c for c, _ in caught), len(caught)
    kinds: dict[str, list[int]] = {}
    for c, t in caught:  # a dataset built before the event's kind was kept says "unknown"
        tally = kinds.setdefault(str(t.get("irreversible_event") or "unknown"), [0, 0])
        tally[0] += int(c)
        tally[1] += 1
    return {
        "irreversible_failures": n,
        "caught_before_irreversible": _share(early, n),
        "caught_before_irreversible_ci": exact_ci(early, n),
        "caught_before_by_event": dict(sorted(kinds.items())),
    }


def _share(k: int, n: int) -> float | None:
    return round(k / n, 4) if n else None


def exact_ci(k: int, n: int) -> list[float] | None:
    """The exact (Clopper-Pearson) 95 % interval of k in n, rounded as the bench's shares are; None when n is 0."""
    from scipy.stats import binomtest

    if not n:
        return None
    ci = binomtest(k, n).proportion_ci(0.95, method="exact")
    return [round(ci.low, 4), round(ci.high, 4)]
