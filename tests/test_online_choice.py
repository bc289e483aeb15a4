"""Choosing the online bench's reported alarm on the calibration split alone: cross-fitting by pair against a
calibration worked out fold by fold, and the rule on hand-made candidates."""

import numpy as np
import pytest

from labrobfail_vlm.alarm import conformal_threshold
from labrobfail_vlm.bench.online_choice import Candidate, choose, crossfit, fold_of, targets_met
from labrobfail_vlm.bench.online_page import choice_md

FRAMES = [1.0, 2.0, 3.0]


def _pairs(n: int) -> list[dict]:
    """n success/failure twins; each failure's onset is its first grid frame (1.4 s) and a spill follows at 1.6 s."""
    out = []
    for i in range(n):
        base = {"group": f"seen-pair{i:07d}", "frame_times_s": FRAMES, "irreversible_event": None}
        none = {"frame": None, "onset_s": None, "irreversible_s": None}
        out.append({**base, "trajectory": f"s{i}", "success": True, **none})
        out.append(
            {**base, "trajectory": f"f{i}", "success": False, "frame": 1, "onset_s": 1.4, "irreversible_s": 1.6}
            | {"irreversible_event": "spill"}
        )
    return out


def test_cross_fitting_scores_each_fold_by_an_alarm_calibrated_on_the_other_folds():
    """Random success scores: the pooled false alarms are those a threshold set on the other folds' successes gives,
    fold by fold (a different count from calibrating on all of them); twins share a fold; every trajectory is
    scored once."""
    trajs = _pairs(300)
    rng = np.random.default_rng(3)
    scores = [list(rng.uniform(0, 0.5, 3)) if t["success"] else [0.1, 0.8, 0.8] for t in trajs]
    got = crossfit(Candidate([scores]), trajs, alpha=0.05, folds=5)
    fold = [fold_of(t["group"], 5) for t in trajs]
    assert all(fold[i] == fold[i + 1] for i in range(0, len(trajs), 2))  # twins together
    assert len(set(fold)) == 5 and fold == [fold_of(t["group"], 5) for t in trajs]  # all used, the same every call
    expected = {None: 0, 0.1: 0}  # marginal, and training-conditional at delta 0.1 (a candidate carries the bench's)
    for f in range(5):
        cal = [max(s) for s, t, x in zip(scores, trajs, fold) if t["success"] and x != f]
        for d in expected:
            th = conformal_threshold(cal, 0.05, d)
            expected[d] += sum(max(s) > th for s, t, x in zip(scores, trajs, fold) if t["success"] and x == f)
    assert got["successes"] == 300 and got["failures"] == 300
    assert got["false_alarm_rate"] == pytest.approx(expected[None] / 300, abs=1e-4) and expected[None] > 0
    tight = crossfit(Candidate([scores]), trajs, alpha=0.05, folds=5, delta=0.1)["false_alarm_rate"]
    assert tight == pytest.approx(expected[0.1] / 300, abs=1e-4) and expected[0.1] < expected[None]
    assert got["detection_rate"] == 1.0 and got["latency_frames_median"] == 1.0  # fired at the second frame
    assert got["caught_before_by_event"] == {"spill": [0, 300]}  # at 2 s, after the spill at 1.6 s


def test_the_rule_picks_the_most_targets_met_then_detection_and_keeps_the_first_of_equals():
    """Three hand-made alarms on one calibration split: one that fires on every failure at its last frame (late:
    latency 2 frames, no spill caught before), one that never fires, one that fires at the onset frame (all four
    targets). The rule takes the third; of two equal candidates, the first in the bench's order."""
    trajs = _pairs(100)
    flat = [[0.2] * 3 if t["success"] else None for t in trajs]  # every success at 0.2: no false alarm anywhere
    late = Candidate([[s or [0.1, 0.1, 0.9] for s in flat]])
    never = Candidate([[s or [0.1, 0.1, 0.1] for s in flat]])
    early = Candidate([[s or [0.9, 0.9, 0.9] for s in flat]])
    res = choose({"late": late, "never": never, "early": early}, trajs)
    assert res["chosen"] == "early" and res["alpha"] == 0.05 and res["folds"] == 5
    cand = res["candidates"]
    assert cand["early"]["targets_met"] == ["false alarms", "detection", "latency", "spills and falls"]
    assert cand["late"]["targets_met"] == ["false alarms", "detection"] and cand["late"]["latency_frames_median"] == 2
    assert cand["never"]["targets_met"] == ["false alarms"] and cand["never"]["detection_rate"] == 0.0
    assert cand["early"]["spills_and_falls"] == [100, 100] and cand["late"]["spills_and_falls"] == [0, 100]
    assert choose({"late": late, "late again": late}, trajs)["chosen"] == "late"
    page = choice_md({"calibration": "val", "chosen_on_calibration": res})
    assert any("**early**" in line for line in page)
    assert "| late | 0.0 | 100.0 | 2 | 0 of 100 | 2 of 4 |" in page


def test_targets_read_from_a_row_by_its_points():
    """A row at 5.0 % false alarms meets that target, at 5.1 % it does not; breakages are not spills or falls."""
    row = {
        "false_alarm_rate": 0.05,
        "detection_rate": 0.8,
        "latency_frames_median": 1.0,
        "caught_before_by_event": {"spill": [5, 7], "fall": [1, 3], "breakage": [0, 11]},
    }
    assert targets_met(row) == ["false alarms", "detection", "latency", "spills and falls"]
    assert targets_met(row | {"false_alarm_rate": 0.051}) == ["detection", "latency", "spills and falls"]
    assert targets_met(row | {"caught_before_by_event": {"spill": [5, 7], "fall": [0, 3]}})[-1] == "latency"
    assert targets_met({"false_alarm_rate": None, "detection_rate": None, "latency_frames_median": None}) == []
