"""The calibrated alarm's false-alarm bound on synthetic scores, and the recovery table's paired statistics
(exact McNemar p, Agresti-Min interval) on tables worked out by hand."""

import math

import numpy as np
import pytest

from labrobfail_vlm.alarm import (
    Alarm,
    AnyAlarm,
    conformal_rank,
    conformal_threshold,
    false_alarm_pvalue,
    first_alarm,
    min_calibration,
)
from sim_backends.supervision.paired import difference_ci, mcnemar_exact, paired_cell


def test_threshold_is_the_conformal_order_statistic():
    s = list(range(1, 20))  # n = 19 maxima 1..19
    assert conformal_threshold(s, 0.05) == 19  # ceil(20 * 0.95) = 19th smallest
    assert conformal_threshold(s, 0.1) == 18  # ceil(20 * 0.9) = 18
    assert conformal_threshold(s, 0.2) == 16
    assert math.isinf(conformal_threshold(s[:18], 0.05))  # ceil(19 * 0.95) = 19 > 18: no finite bound
    assert min_calibration(0.05) == 19 and min_calibration(0.01) == 99 and min_calibration(0.2) == 4
    assert first_alarm([0.1, 0.5, 0.9, 0.95], 0.5) == 2 and first_alarm([0.1, 0.2], 0.5) is None
    with pytest.raises(ValueError, match="alpha"):
        conformal_threshold(s, 1.0)


def _successes(rng, k):
    """Running scores of successful trajectories: random lengths, a random walk squashed into (0, 1)."""
    return [1 / (1 + np.exp(-np.cumsum(rng.normal(-0.2, 0.6, rng.integers(3, 17))))) for _ in range(k)]


@pytest.mark.parametrize("alpha", [0.01, 0.05, 0.1, 0.2])
def test_false_alarm_rate_on_new_successes_is_within_the_bound(alpha):
    """Averaged over calibration draws, the alarm fires on at most alpha of new exchangeable successes, and (the
    scores being continuous) on at least alpha - 1/(n+1): the bound is tight, not vacuous."""
    rng = np.random.default_rng(int(alpha * 1000))
    n = max(min_calibration(alpha), 40)
    rates = []
    for _ in range(300):
        alarm = Alarm.calibrate(_successes(rng, n), alpha)
        assert alarm.n_calibration == n and math.isfinite(alarm.threshold)
        rates.append(np.mean([alarm.fires(s) is not None for s in _successes(rng, 100)]))
    mean, se = float(np.mean(rates)), float(np.std(rates) / np.sqrt(len(rates)))
    assert alpha - 1 / (n + 1) - 3 * se <= mean <= alpha + 3 * se, (alpha, n, mean, se)


def test_the_bound_check_is_exact_on_known_cases_and_valid_under_exchangeability():
    """false_alarm_pvalue: one new success raises an alarm set at 0.1 on 19 successes with probability 2/20 exactly;
    a threshold too high to be finite never fires. On synthetic draws: with exchangeable successes the p-values are
    (super-)uniform, so p < 0.05 comes up at most 5 % of the time, and P(at least k false alarms) matches the count's
    frequency; with new successes scored higher (a shift: a new scene), the check flags them. A pair's union bound
    is valid too."""
    assert false_alarm_pvalue(19, 0.1, 1, 1) == pytest.approx(0.1)
    assert false_alarm_pvalue(19, 0.1, 0, 50) == 1.0
    assert false_alarm_pvalue(18, 0.05, 0, 30) == 1.0 and false_alarm_pvalue(18, 0.05, 1, 30) == 0.0
    assert false_alarm_pvalue(0, 0.05, 0, 30) == 1.0  # no calibration success: the alarm never fires
    with pytest.raises(ValueError, match="false alarms"):
        false_alarm_pvalue(19, 0.1, 5, 4)
    rng = np.random.default_rng(3)
    n, m, alpha, reps = 40, 60, 0.1, 2000
    counts, shifted = [], []
    for _ in range(reps):
        th = Alarm.calibrate([[x] for x in rng.random(n)], alpha).threshold
        counts.append(int(np.sum(rng.random(m) > th)))
        shifted.append(int(np.sum(rng.random(m) ** 0.25 > th)))  # scored higher: false alarms ~34 % at alpha 0.1
    p_of = np.asarray([false_alarm_pvalue(n, alpha, k, m) for k in range(m + 1)])  # per count, once
    counts_a = np.asarray(counts)
    assert np.mean(p_of[counts_a] < 0.05) <= 0.05 + 3 * np.sqrt(0.05 * 0.95 / reps)
    for k in (3, 6, 9, 12):
        freq = float(np.mean(counts_a >= k))
        assert abs(freq - p_of[k]) <= 3 * np.sqrt(freq * (1 - freq) / reps) + 1e-3, k
    assert np.mean(p_of[np.asarray(shifted)] < 0.05) > 0.7
    # two monitors at alpha / 2 (a pair): a union bound, so valid whatever their dependence (here independent)
    assert false_alarm_pvalue(19, 0.2, 1, 1, monitors=2) == pytest.approx(0.2)  # 2 x P(one fires) = 2 x 2/20
    pair_ks = []
    for _ in range(500):
        pair = AnyAlarm.calibrate([[[x] for x in rng.random(n)], [[x] for x in rng.random(n)]], alpha)
        k = sum(pair.fires([[a], [b]]) is not None for a, b in rng.random((m, 2)))
        pair_ks.append(k)
    pair_p = np.asarray([false_alarm_pvalue(n, alpha, k, m, monitors=2) for k in range(m + 1)])
    assert np.mean(pair_p[np.asarray(pair_ks)] < 0.05) <= 0.05 + 3 * np.sqrt(0.05 * 0.95 / 500)
    assert false_alarm_pvalue(n, alpha, 40, m, monitors=2) < 1e-3  # 40 of 60: flagged


def test_a_training_conditional_alarm_keeps_its_rate_under_alpha_on_all_but_delta_of_calibration_draws():
    """Uniform scores (one per trajectory) make an alarm's rate on new successes exactly 1 - its threshold. Over
    2,000 calibration draws of n = 400, the marginal alarm's rate is over alpha = 0.05 on about half of them (its
    bound holds on average only), the one with delta = 0.1 on at most a tenth (the share its rank's Beta law gives),
    and its bound check and a pair's union over deltas follow. Known ranks: the smallest n with a finite threshold."""
    from scipy.stats import beta

    assert conformal_rank(45, 0.05, 0.1) == 45 and conformal_rank(44, 0.05, 0.1) == 45  # 0.95 ** 45 < 0.1 < 0.95 ** 44
    assert min_calibration(0.05, 0.1) == 45 and math.isinf(conformal_threshold(list(range(44)), 0.05, 0.1))
    for a, d in [(0.1, 0.5), (0.05, 0.9), (0.05, 0.95**20), (0.5, 0.5**29), (0.01, None), (0.2, 0.01)]:
        n = min_calibration(a, d)  # the first n with a finite threshold, read from the same floats as the rank
        assert conformal_rank(n, a, d) <= n and conformal_rank(n - 1, a, d) > n - 1, (a, d, n)
    with pytest.raises(ValueError, match="delta"):
        conformal_rank(100, 0.05, 1.0)
    rng = np.random.default_rng(11)
    n, alpha, delta, reps = 400, 0.05, 0.1, 2000
    r = conformal_rank(n, alpha, delta)
    assert r > conformal_rank(n, alpha) and beta.sf(alpha, n + 1 - r, r) <= delta < beta.sf(alpha, n + 2 - r, r - 1)
    over = {None: 0, delta: 0}
    for _ in range(reps):
        cal = [[x] for x in rng.random(n)]
        for d in over:
            alarm = Alarm.calibrate(cal, alpha, d)
            over[d] += 1 - alarm.threshold > alpha
    se = np.sqrt(0.25 / reps)
    assert over[None] / reps > 0.4  # the marginal alarm: over alpha on ~half the draws
    exact = beta.sf(alpha, n + 1 - r, r)
    assert abs(over[delta] / reps - exact) <= 3 * se and over[delta] / reps <= delta + 3 * se
    assert Alarm.calibrate([[0.5]] * n, alpha, delta).to_dict()["delta"] == delta
    assert "delta" not in Alarm.calibrate([[0.5]] * n, alpha).to_dict()  # a marginal alarm's JSON as before
    # the bound check reads the raised rank (386 of 400, not 381): 32 false alarms of 500 are likely at the
    # marginal rank, not at delta's
    assert false_alarm_pvalue(n, alpha, 32, 500) > 0.05 > false_alarm_pvalue(n, alpha, 32, 500, deltas=[delta])
    pair = AnyAlarm.calibrate([cal, cal], alpha, (0.2, 0.8), delta)
    assert [a.delta for a in pair.alarms] == pytest.approx([0.02, 0.08])
    assert pair.to_dict()["deltas"] == pytest.approx([0.02, 0.08])


def test_two_monitors_share_one_bound_and_the_pair_fires_at_the_earlier_alarm():
    """Each monitor is calibrated at alpha / 2 on the same successes: on new successes the pair fires on at most
    alpha of them (union bound; independent monitors come close to it), and on a trajectory it fires at the first
    keyframe either fires. One monitor is that monitor's own Alarm at alpha."""
    rng = np.random.default_rng(7)
    alpha, n = 0.1, 60
    rates = []
    for _ in range(300):
        pair = AnyAlarm.calibrate([_successes(rng, n), _successes(rng, n)], alpha)
        assert [a.alpha for a in pair.alarms] == [alpha / 2, alpha / 2]
        new = zip(_successes(rng, 100), _successes(rng, 100))
        rates.append(np.mean([pair.fires(s) is not None for s in new]))
    mean, se = float(np.mean(rates)), float(np.std(rates) / np.sqrt(len(rates)))
    assert alpha - 2 / (n + 1) - 3 * se <= mean <= alpha + 3 * se, (mean, se)
    pair = AnyAlarm((Alarm(0.05, 0.5, 40), Alarm(0.05, 0.8, 40)))
    assert pair.fires([[0.1, 0.2, 0.6, 0.9], [0.1, 0.9, 0.1, 0.1]]) == 1  # the second monitor fires first
    assert pair.fires([[0.1, 0.2, 0.6, 0.9], [0.1, 0.1, 0.1, 0.1]]) == 2
    assert pair.fires([[0.1, 0.2], [0.3, 0.4]]) is None
    assert pair.to_dict() == {"alpha": 0.1, "thresholds": [0.5, 0.8], "n_calibration": 40, "alphas": [0.05, 0.05]}
    one = _successes(rng, n)
    assert AnyAlarm.calibrate([one], alpha).alarms == (Alarm.calibrate(one, alpha),)
    with pytest.raises(ValueError, match="same calibration successes"):
        AnyAlarm.calibrate([one, one[:-1]], alpha)


def test_a_monitor_checked_between_frames_sounds_before_an_event_the_frames_miss():
    """Hand-made trajectories with grid frames at 1, 2 and 3 s: a failure whose onset (1.4 s) comes 0.2 s before an
    irreversible event (1.6 s). A per-frame monitor can sound at 2 s at the earliest, after the event; one checked
    every 0.1 s sounds at 1.5 s, before it. The model's per-frame score placed on the trace's times stands from
    one frame to the next and keeps its calibration (same maxima)."""
    from labrobfail_vlm.bench.online_alarm import alarm_rows, on_axis, sounded

    frames = [1.0, 2.0, 3.0]
    axis = np.round(np.arange(1, 31) / 10, 4)  # 0.1 .. 3.0 s
    succ = {"success": True, "frame": None, "frame_times_s": frames, "onset_s": None, "irreversible_s": None}
    fail = {**succ, "success": False, "frame": 2, "onset_s": 1.4, "irreversible_s": 1.6}
    cal_t = [succ] * 40
    rng = np.random.default_rng(0)
    cal_dense = [rng.uniform(0, 0.5, len(axis)) for _ in cal_t]  # every threshold under 0.5
    ramp = np.where(axis >= 1.45, 0.9, 0.1)  # the failure's dense score rises at 1.5 s
    ev_t = [fail, succ]
    dense = alarm_rows([cal_dense], cal_t, [[ramp, np.full(len(axis), 0.2)]], ev_t, [axis, axis])["0.1"]
    assert dense["detection_rate"] == 1.0 and dense["false_alarm_rate"] == 0.0
    assert dense["latency_s_median"] == pytest.approx(0.1) and dense["latency_frames_median"] == 0  # by frame 2
    assert dense["caught_before_irreversible"] == 1.0 and dense["irreversible_failures"] == 1
    per_frame = alarm_rows([[[0.1] * 3] * 40], cal_t, [[[0.1, 0.9, 0.9], [0.1] * 3]], ev_t)["0.1"]
    assert per_frame["latency_s_median"] == pytest.approx(0.6) and per_frame["caught_before_irreversible"] == 0.0
    stand = on_axis([0.1, 0.9, 0.3], frames, axis)
    assert np.all(np.isinf(stand[:9])) and stand[9] == 0.1 and stand[19] == 0.9 and stand[-1] == 0.3
    assert stand.max() == 0.9 and set(np.unique(stand[np.isfinite(stand)])) == {0.1, 0.3, 0.9}
    assert sounded(14, fail, axis) == (1, 1.5) and sounded(0, fail, None) == (0, 1.0)
    assert sounded(29, fail, axis) == (2, 3.0) and sounded(None, fail, axis) == (None, None)
    pair = alarm_rows(
        [[on_axis([0.1] * 3, frames, axis)] * 40, cal_dense],
        cal_t,
        [[on_axis([0.1, 0.9, 0.9], frames, axis), on_axis([0.1] * 3, frames, axis)], [ramp, np.full(len(axis), 0.2)]],
        ev_t,
        [axis, axis],
    )["0.1"]
    assert pair["caught_before_irreversible"] == 1.0 and len(pair["thresholds"]) == 2


def test_the_share_caught_before_an_irreversible_event_carries_its_exact_interval():
    """Nine hand-made failures with an event at 1.6 s (six breakages, three spills), five caught at 1.5 s and four
    at 2 s: 5 of 9 with its Clopper-Pearson 95 % interval [0.212, 0.863] (a known table), in the JSON and on the
    page's line, and per kind; the ceiling (the labeler at each onset: 1.4 s in the breakages, 1.6 s, the spill
    itself, in the spills) reads 6 of 9 [0.299, 0.925], none of the spills; no such failure, no interval."""
    from labrobfail_vlm.bench.online_alarm import ceiling, timing
    from labrobfail_vlm.bench.online_page import online_md

    frames = [1.0, 2.0, 3.0]
    fail = {"success": False, "frame": 1, "frame_times_s": frames, "onset_s": 1.4, "irreversible_s": 1.6}
    fails = [{**fail, "irreversible_event": "breakage"}] * 6 + [{**fail, "irreversible_event": "spill"}] * 3
    trajs = [*fails, {**fail, "success": True, "frame": None, "onset_s": None, "irreversible_s": None}]
    got = timing([1.5] * 5 + [2.0] * 4 + [None], trajs)
    assert got["irreversible_failures"] == 9 and got["caught_before_irreversible"] == pytest.approx(5 / 9, abs=1e-4)
    assert got["caught_before_irreversible_ci"] == pytest.approx([0.212, 0.863], abs=5e-4)
    assert got["caught_before_by_event"] == {"breakage": [5, 6], "spill": [0, 3]}
    late = [{**t, "onset_s": 1.6} if t.get("irreversible_event") == "spill" else t for t in trajs]
    top = ceiling(late)
    assert top["caught_before_irreversible"] == pytest.approx(6 / 9, abs=1e-4)
    assert top["caught_before_irreversible_ci"] == pytest.approx([0.2993, 0.9251], abs=5e-4)
    assert top["caught_before_by_event"] == {"breakage": [6, 6], "spill": [0, 3]}
    assert timing([None], [{**fail, "irreversible_s": None}])["caught_before_irreversible_ci"] is None
    assert timing([1.5], [fail])["caught_before_by_event"] == {"unknown": [1, 1]}  # a dataset without kinds
    frames_at = {"latency_frames_median": 0, "latency_frames_p90": 1, "caught_by_onset": 0.0}
    # false alarms from their count (2 of 40), detection from a JSON without one (its rate times n: 5 of 9)
    rates = {"false_alarm_rate": 0.05, "false_alarms": 2, "successes": 40, "detection_rate": 0.5556, "failures": 9}
    res = {
        "split": "test",
        "trajectories": 10,
        "calibration_successes": 40,
        "calibration": "val",
        "rows": {
            "robot signals (MLP)": {"0.05": {**got, **rates, **frames_at}},
            "labeler on live state (ceiling)": {**top, "false_alarm_rate": 0.0},
        },
    }
    page = online_md(res)
    line = [x for x in page if x.startswith("| labeler")]
    assert line[0].endswith("| 66.7 [29.9, 92.5] (of 9) |"), line
    line = [x for x in page if x.startswith("| robot signals (MLP) | 0.05 |")]
    assert line and line[0].endswith("| 55.6 [21.2, 86.3] (of 9) |"), line
    assert (
        line[0].startswith("| robot signals (MLP) | 0.05 | 5.0 [0.6, 16.9] | ")
        and "| 55.6 [21.2, 86.3] | 0 / 1 |" in line[0]
    )
    # the spills and falls pooled (the target's figure), 0 of 3 with its exact interval [0, 1 - 0.025 ** (1 / 3)]
    assert page[page.index("| row | spill | breakage | spills and falls (%) |") + 2 :] == [
        "| robot signals (MLP) | 0 of 3 | 5 of 6 | 0.0 [0.0, 70.8] (0 of 3) |",
        "| labeler on live state (ceiling) | 0 of 3 | 6 of 6 | 0.0 [0.0, 70.8] (0 of 3) |",
    ]


def test_mcnemar_and_the_difference_interval_on_known_tables():
    assert mcnemar_exact(1, 9) == pytest.approx(22 / 1024)  # 2 * (C(10,0) + C(10,1)) / 2^10
    assert mcnemar_exact(0, 6) == pytest.approx(2 / 64)
    assert mcnemar_exact(5, 5) == 1.0 and mcnemar_exact(0, 0) == 1.0
    lo, hi = difference_ci(1, 9, 100)  # Agresti-Min: (9.5 - 1.5) / 102 +- 1.96 * sqrt(11 - 64/102) / 102
    assert (lo, hi) == pytest.approx((0.016545, 0.140317), abs=1e-5)
    assert difference_ci(0, 0, 10)[0] < 0 < difference_ci(0, 0, 10)[1]
    without = [True] * 60 + [False] * 40
    with_sup = [True] * 59 + [False] + [True] * 10 + [False] * 30  # one success broken, ten failures rescued
    cell = paired_cell(without, with_sup)
    assert (cell.n, cell.broken, cell.rescued, cell.base_successes, cell.supervised_successes) == (100, 1, 10, 60, 69)
    s = cell.summary()
    assert s["gain_points"] == 9.0 and s["mcnemar_p"] == pytest.approx(mcnemar_exact(1, 10))
    assert s["broken_share"] == pytest.approx(1 / 60, abs=1e-4) and s["ci95_points"][0] > 0
    none_succeed = paired_cell([False] * 5, [False, True, False, False, False]).summary()
    assert none_succeed["broken_share"] is None and none_succeed["rescued"] == 1  # nothing to break is no 0 %
    with pytest.raises(ValueError, match="same"):
        paired_cell([True], [True, False])


@pytest.mark.parametrize("k", [1, 3, 8])
def test_a_prefix_grid_cut_from_the_whole_grid_is_the_one_the_dataset_builds(k):
    from labrobfail_vlm.bench.online import prefix_grid
    from labrobfail_vlm.grid import GridConfig, build_grid

    cfg = GridConfig(width=512, height=512, max_frames=8, columns=4)
    rng = np.random.default_rng(k)
    frames = [[rng.integers(0, 255, (64, 64, 3), dtype=np.uint8) for _ in range(8)] for _ in range(2)]
    got = prefix_grid(build_grid(frames, cfg), cfg, 2, k)
    assert np.array_equal(np.asarray(got), np.asarray(build_grid(frames, cfg, visible=k)))


def test_a_pair_may_split_alpha_unevenly_and_keeps_the_bound():
    """Monitor i at alpha * shares[i]: the thresholds follow the shares, the pair's false-alarm rate on new
    successes stays within alpha, and the bound check reads each monitor's own level (one that can never fire adds
    nothing), the rank its threshold was set at. Bad shares are refused."""
    rng = np.random.default_rng(11)
    alpha, n = 0.1, 60
    rates = []
    for _ in range(300):
        pair = AnyAlarm.calibrate([_successes(rng, n), _successes(rng, n)], alpha, shares=(0.8, 0.2))
        assert [a.alpha for a in pair.alarms] == pytest.approx([0.08, 0.02])
        new = zip(_successes(rng, 100), _successes(rng, 100))
        rates.append(np.mean([pair.fires(s) is not None for s in new]))
    mean, se = float(np.mean(rates)), float(np.std(rates) / np.sqrt(len(rates)))
    assert alpha - 2 / (n + 1) - 3 * se <= mean <= alpha + 3 * se, (mean, se)
    # n = 19, alpha 0.2 split 0.18 / 0.02: the first monitor's threshold is the 17th of 19 (P(fire) = 3/20); the
    # second needs 49 successes (+inf), so it adds nothing; halves read 2/20 + 2/20
    p = false_alarm_pvalue(19, 0.2, 1, 1, monitors=2, alphas=(0.18, 0.02))
    assert p == pytest.approx(0.15) and false_alarm_pvalue(19, 0.2, 1, 1, monitors=2) == pytest.approx(0.2)
    assert false_alarm_pvalue(19, 0.2, 1, 1, monitors=2, alphas=(0.15, 0.05)) == pytest.approx(0.2)  # 3/20 + 1/20
    # two false alarms of two: either the first fires on both (P = C(2,2) tail) or each once (3/20 + 1/20 bound)
    both = false_alarm_pvalue(19, 0.2, 2, 2, monitors=2, alphas=(0.15, 0.05))
    assert 0 < both < false_alarm_pvalue(19, 0.2, 1, 2, monitors=2, alphas=(0.15, 0.05)) <= 1
    # the levels a pair was set at read back the ranks of its thresholds, even where alpha * share is not exact
    maxima = [_successes(rng, 999), _successes(rng, 999)]
    pair = AnyAlarm.calibrate(maxima, 0.1, shares=(0.41, 0.59))
    row = pair.to_dict()
    for i, (a, s) in enumerate(zip(pair.alarms, maxima)):
        assert a.threshold == np.sort([max(x) for x in s])[conformal_rank(999, row["alphas"][i]) - 1]
    assert false_alarm_pvalue(999, row["alpha"], 0, 50, monitors=2, alphas=row["alphas"]) == 1.0
    for bad in ((0.5, 0.6), (1.0,), (-0.2, 1.2), (0.0, 1.0)):
        with pytest.raises(ValueError, match="shares"):
            AnyAlarm.calibrate([_successes(rng, n), _successes(rng, n)], alpha, shares=bad)


def test_the_online_table_names_the_monitors_that_cannot_fire():
    """A monitor whose level is too small for its calibration set has a +inf threshold (null in the JSON): the
    table says so under it, naming which of a pair's monitors, rather than let the row read as a weak monitor."""
    from labrobfail_vlm.bench.online_page import online_md

    def row(**kw):
        return {"false_alarm_rate": 0.0, "detection_rate": 0.5, "latency_frames_median": 0.0, "n_calibration": 192} | kw

    rows = {
        "model": {"0.01": row(threshold=0.9, alpha=0.01), "0.05": row(threshold=0.8, alpha=0.05)},
        "pair": {
            "0.01": row(thresholds=[None, None], alpha=0.01),
            "0.05": row(thresholds=[None, 0.7], alpha=0.05),
            "0.1": row(thresholds=[0.6, 0.7], alpha=0.1),
        },
        "labeler on live state (ceiling)": {"false_alarm_rate": 0.0, "detection_rate": 1.0},
    }
    res = {"split": "test", "trajectories": 3, "calibration_successes": 192, "calibration": "val", "rows": rows}
    last = online_md(res)[-1]
    assert last.startswith("Never fires") and last.endswith(": pair at alpha 0.01 (both), 0.05 (the model).")
    rows["pair"] = {"0.1": row(thresholds=[0.6, 0.7], alpha=0.1)}
    assert not any(line.startswith("Never fires") for line in online_md(res))  # nothing to say: no line


def test_the_two_mlps_paired_sound_when_either_does_each_at_half_of_alpha():
    """40 calibration successes scoring under 0.5 on both monitors; three failures: the per-frame MLP alone reads
    the first (0.9 from its second frame), the every-sample MLP alone the second (0.9 between frames, from 2.5 s),
    neither the third. At alpha 0.2 each monitor is set at 0.1 and the pair detects exactly the first two."""
    from labrobfail_vlm.bench.online import _with_dense

    rng = np.random.default_rng(0)
    frames = [1.0, 2.0, 3.0]
    axis = np.round(np.arange(0.5, 3.01, 0.25), 4)  # the trace's samples (s)
    none = {"frame": None, "onset_s": None, "irreversible_s": None}
    cal_t = [{"trajectory": f"s{i}", "success": True, "frame_times_s": frames, **none} for i in range(40)]
    cal = ([list(rng.uniform(0, 0.5, 3)) for _ in cal_t], [rng.uniform(0, 0.5, len(axis)) for _ in cal_t])
    fail = {"success": False, "frame": 1, "frame_times_s": frames, "onset_s": 1.9, "irreversible_s": None}
    ev_t = [{**fail, "trajectory": f"f{i}"} for i in range(3)]
    low = np.full(len(axis), 0.1)
    ev = ([[0.1, 0.9, 0.9], [0.1] * 3, [0.1] * 3], [low, np.where(axis >= 2.5, 0.9, 0.1), low])
    rows, cand = _with_dense((cal[0], ev[0]), (cal[1], ev[1]), (cal_t, ev_t), ([axis] * 40, [axis] * 3), 0.5, None)
    row = rows["0.2"]
    assert row["alphas"] == [0.1, 0.1] and row["detected"] == 2 and row["detection_rate"] == round(2 / 3, 4)
    assert all(0.1 < t < 0.9 for t in row["thresholds"]) and cand.shares == (0.5, 0.5) and len(cand.cal) == 2


def test_a_rate_reads_its_count_and_an_older_json_its_rate_times_n_only_under_10000():
    """The page's intervals: from the JSON's count where it has one; from a 4-digit rate times n below 10,000
    (3,000 x 0.0333 = 99.9 -> 100); above, no count can be trusted and no interval is drawn."""
    from labrobfail_vlm.bench.online_alarm import count_of
    from labrobfail_vlm.bench.online_page import _rate

    keys = ("false_alarm_rate", "false_alarms", "successes")
    big = {"false_alarm_rate": 0.0333, "successes": 10_000}
    assert count_of(big, *keys) is None and _rate(big, *keys) == "3.3"
    assert _rate({**big, "false_alarms": 333}, *keys) == "3.3 [3.0, 3.7]"
    small = {"false_alarm_rate": 0.0333, "successes": 3_000}
    assert count_of(small, *keys) == 100 and _rate(small, *keys) == "3.3 [2.7, 4.0]"
    assert count_of({**small, "false_alarms": 7}, *keys) == 7  # the count wins over the rate
