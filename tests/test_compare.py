"""labrobfail-compare: two models' benches compared by pair, on a hand-made split whose differences are known."""

import json

import numpy as np
from conftest import cli, evaluate, run, run_here

Q2 = "Task: pick up the beaker. Is there any anomaly or failure observed in this trajectory? (Yes/No)"
GOLD_FAILED = {"Q2": "Yes", "Q3": "3", "Q4": "2", "Q5": "1", "Q6": "Regrasp the beaker and place it again."}
GOLD_OK = {"Q2": "No", "Q3": "None", "Q4": "None", "Q5": "None", "Q6": "No correction is needed."}
PAIRS = 4


def _dataset(root):
    """PAIRS success/failure pairs in split val: trajectory p<i>-ok and p<i>-fail, pair p<i>."""
    traj, recs = [], []
    for i in range(PAIRS):
        for kind, gold in (("ok", GOLD_OK), ("fail", GOLD_FAILED)):
            t = f"p{i}-{kind}"
            traj.append({"trajectory": t, "group": f"p{i}", "success": kind == "ok", "split": "val"})
            for d, ans in gold.items():
                q = Q2 if d == "Q2" else f"Task: pick up the beaker. Question {d}."
                recs.append({"id": f"{t}_{d}", "conversations": [{"value": q}, {"value": ans}]})
    root.mkdir(parents=True)
    (root / "trajectories.json").write_text(json.dumps(traj))
    (root / "val.json").write_text(json.dumps(recs))
    return recs


def _write(model, recs, reply, p_failure, split="val"):
    out = model / f"eval_{split}"
    out.mkdir(parents=True)
    with open(out / "predictions.jsonl", "w") as f:
        for r in recs:
            t, d = r["id"].rsplit("_", 1)
            f.write(json.dumps({"id": r["id"], "prediction": reply(t, d, r), "p_failure": p_failure(t)}) + "\n")


def compare(tmp_path, *extra):
    return run_here(
        [
            cli("compare"),
            f"a={tmp_path / 'a'}",
            f"b={tmp_path / 'b'}",
            f"dataset_dir={tmp_path / 'ds'}",
            "splits=[val]",
            "resamples=500",
            *extra,
        ]
    )


def test_differences_and_paired_intervals_on_a_known_split(tmp_path):
    recs = _dataset(tmp_path / "ds")
    gold = lambda t, d, r: r["conversations"][1]["value"]  # noqa: E731
    fails = lambda t: 0.9 if t.endswith("fail") else 0.1  # noqa: E731

    def a_reply(t, d, r):  # pair p0 inverted on Q2 (its failure missed, its success right); Q3 never answered
        if t == "p0-fail" and d == "Q2":
            return "No"
        return "None" if d == "Q3" else gold(t, d, r)

    def b_reply(t, d, r):  # the same Q2 count as a, but in pair p0 the other twin wrong: a false alarm instead
        return "Yes" if t == "p0-ok" and d == "Q2" else gold(t, d, r)

    _write(tmp_path / "a", recs, a_reply, fails)
    _write(tmp_path / "b", recs, b_reply, lambda t: 1 - fails(t))  # b ranks every trajectory backwards
    r = compare(tmp_path, f"out={tmp_path / 'cmp.json'}")
    assert r.returncode == 0, r.stderr
    res = json.loads((tmp_path / "cmp.json").read_text())["splits"]["val"]
    assert res["pairs"] == PAIRS and res["trajectories"] == 2 * PAIRS
    # Q2: both models miss one trajectory of the same pair; drawn together, the difference is 0 in every resample
    assert res["Q2"] == {"a": 87.5, "b": 87.5, "diff": 0.0, "ci95": [0.0, 0.0]}
    assert res["recall"]["diff"] == 25.0 and res["false_alarms"]["diff"] == 25.0
    assert res["recall"]["ci95"][0] == 0.0 and res["recall"]["ci95"][1] > 25.0  # p0 drawn 0 or 2+ times
    assert res["Q3"] == {"a": 0.0, "b": 100.0, "diff": 100.0, "ci95": [100.0, 100.0]}
    assert res["Q4"]["diff"] == 0.0 and res["rougeL"]["a"] == res["rougeL"]["b"] == 1.0
    assert res["auroc"] == {
        "a": 1.0,
        "b": 0.0,
        "diff": -1.0,
        "ci95": [-1.0, -1.0],
        "score": {"a": "probability", "b": "probability"},
    }
    assert "| val | Q3 | 0.0 | 100.0 | +100.0 [+100.0, +100.0] |" in r.stdout


def test_a_missing_bench_or_reply_is_one_line(tmp_path):
    recs = _dataset(tmp_path / "ds")
    gold = lambda t, d, r: r["conversations"][1]["value"]  # noqa: E731
    _write(tmp_path / "a", recs, gold, lambda t: 0.5)
    r = compare(tmp_path)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines() == [
        f"error: b: {tmp_path / 'b' / 'eval_val' / 'predictions.jsonl'} not found (bench it first: "
        f"labrobfail-evaluate model={tmp_path / 'b'} dataset_dir={tmp_path / 'ds'} split=val)"
    ]
    _write(tmp_path / "b", recs[:-3], gold, lambda t: 0.5)
    r = compare(tmp_path, f"out={tmp_path / 'cmp.json'}")
    assert r.returncode == 2 and "has no reply for 3 of the split's 40 records" in r.stderr
    assert not (tmp_path / "cmp.json").exists()
    r = compare(tmp_path, "resamples=0")
    assert r.returncode == 2 and r.stderr.startswith("error: resamples: expected an integer >= 1")


def test_a_bench_on_grids_of_another_frame_count_is_refused(tmp_path):
    """The same records built with 16 keyframes instead of 8 (5 Dec): a Q3 reply weighing 12 frames where the
    dataset's grid shows 8 was made on other grids, and its Q3 would be scored against the wrong frame numbers."""
    recs = _dataset(tmp_path / "ds")
    traj = json.loads((tmp_path / "ds" / "trajectories.json").read_text())
    (tmp_path / "ds" / "trajectories.json").write_text(json.dumps([{**t, "frames": 8} for t in traj]))
    gold = lambda t, d, r: r["conversations"][1]["value"]  # noqa: E731
    for side, frames in (("a", 8), ("b", 12)):
        out = tmp_path / side / "eval_val"
        out.mkdir(parents=True)
        with open(out / "predictions.jsonl", "w") as f:
            for r in recs:
                t, d = r["id"].rsplit("_", 1)
                line = {"id": r["id"], "prediction": gold(t, d, r), "p_failure": 0.5}
                f.write(json.dumps(line | ({"scores": [0.0] * frames} if d == "Q3" else {})) + "\n")
    r = compare(tmp_path, f"out={tmp_path / 'cmp.json'}")
    assert r.returncode == 2 and "Traceback" not in r.stderr and not (tmp_path / "cmp.json").exists()
    (line,) = r.stderr.strip().splitlines()
    assert line.startswith("error: b: ") and "weighs 12 frames in its Q3 reply to p0-ok_Q3" in line
    assert "the dataset's grid shows 8" in line
    (tmp_path / "b" / "eval_val" / "predictions.jsonl").write_text(
        (tmp_path / "a" / "eval_val" / "predictions.jsonl").read_text()
    )
    assert compare(tmp_path).returncode == 0  # 8 options on 8-frame grids: compared


def test_one_model_at_two_operating_points(tmp_path):
    """b_threshold=val reads the model's eval_<split>_opval bench (the cut chosen on val), beside its 0.5 bench; a
    bad operating point or a missing bench at it is one line naming it."""
    recs = _dataset(tmp_path / "ds")
    gold = lambda t, d, r: r["conversations"][1]["value"]  # noqa: E731
    p = lambda t: 0.4 if t in ("p0-fail", "p1-fail") else 0.1  # noqa: E731  two failures under 0.5, over the cut

    def at_half(t, d, r):  # those two failures missed at 0.5: "No", no diagnosis
        return ("No" if d == "Q2" else GOLD_OK[d]) if t in ("p0-fail", "p1-fail") else gold(t, d, r)

    _write(tmp_path / "a", recs, at_half, p)
    r = compare(tmp_path, f"b={tmp_path / 'a'}", "b_threshold=val")
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        f"error: b: {tmp_path / 'a' / 'eval_val_opval' / 'predictions.jsonl'} not found (bench it first: "
        f"labrobfail-evaluate model={tmp_path / 'a'} dataset_dir={tmp_path / 'ds'} split=val threshold=val)"
    ]
    _write(tmp_path / "a", recs, gold, p, split="val_opval")  # at the cut 0.3 both are caught and diagnosed
    r = compare(tmp_path, f"b={tmp_path / 'a'}", "b_threshold=val", f"out={tmp_path / 'cmp.json'}")
    assert r.returncode == 0, r.stderr
    out = json.loads((tmp_path / "cmp.json").read_text())
    assert (out["a_threshold"], out["b_threshold"]) == (0.5, "val")
    res = out["splits"]["val"]
    assert res["recall"] == {"a": 50.0, "b": 100.0, "diff": 50.0, "ci95": res["recall"]["ci95"]}
    assert res["Q3"]["diff"] == 50.0 and res["false_alarms"]["diff"] == 0.0
    assert f"b = {tmp_path / 'a'} (operating point val)" in r.stdout  # its results.json names no cut here
    (tmp_path / "a" / "eval_val_opval" / "results.json").write_text(json.dumps({"threshold": 0.3}))
    r = compare(tmp_path, f"a={tmp_path / 'a'}", "a_threshold=val", f"b={tmp_path / 'a'}", f"out={tmp_path / 'c.json'}")
    assert r.returncode == 0 and f"a = {tmp_path / 'a'} (operating point val: P(failure) >= 0.300)" in r.stdout
    out = json.loads((tmp_path / "c.json").read_text())
    assert out["a_cut"] == 0.3 and out["splits"]["val"]["recall"]["diff"] == -50.0  # a read at the cut this time
    _write(tmp_path / "a", recs, gold, p, split="val_t0.3")  # a number names its own folder, as the bench writes it
    r = compare(tmp_path, f"b={tmp_path / 'a'}", "b_threshold=0.3", f"out={tmp_path / 'd.json'}")
    assert r.returncode == 0 and json.loads((tmp_path / "d.json").read_text())["splits"]["val"]["Q3"]["diff"] == 50.0
    for bad in ("b_threshold=1.5", "a_threshold=half", "b_threshold=true"):
        r = compare(tmp_path, f"b={tmp_path / 'a'}", bad)
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert f"{bad.split('=')[0]}: expected val or a number" in r.stderr  # "between 0 and 1" from its reader


def test_the_a_side_equals_the_bench_of_the_same_replies(tmp_path):
    """labrobfail-evaluate's figures of a predictions file and compare's (a real process) for the same replies
    agree, with errors scattered over both twins of several pairs."""
    recs = _dataset(tmp_path / "ds")
    rng = np.random.default_rng(1)
    wrong = {"Q2": "No", "Q3": "5", "Q4": "4", "Q5": "3", "Q6": "Close the oven door."}

    def noisy(t, d, r):
        return wrong[d] if rng.random() < 0.4 else r["conversations"][1]["value"]

    (tmp_path / "p").mkdir()
    _write(tmp_path / "p", recs, noisy, lambda t: float(rng.random()))
    preds = tmp_path / "p" / "eval_val" / "predictions.jsonl"
    r = evaluate(
        f"predictions={preds}",
        tmp_path / "ds",
        "split=val",
        "baselines=[]",
        "q6_template=false",
        f"out_dir={tmp_path / 'a' / 'eval_val'}",
        "progress=false",
        call=run_here,  # the bench as a process is tested elsewhere; compare runs as one below
    )
    assert r.returncode == 0, r.stderr[-2000:]
    bench = json.loads((tmp_path / "a" / "eval_val" / "results.json").read_text())
    _write(tmp_path / "b", recs, lambda t, d, r: r["conversations"][1]["value"], lambda t: 0.5)
    r = run(
        [
            cli("compare"),
            f"a={tmp_path / 'a'}",
            f"b={tmp_path / 'b'}",
            f"dataset_dir={tmp_path / 'ds'}",
            "splits=[val]",
            f"out={tmp_path / 'cmp.json'}",
        ],
        300,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    a = {
        k: v["a"]
        for k, v in json.loads((tmp_path / "cmp.json").read_text())["splits"]["val"].items()
        if isinstance(v, dict)
    }
    fo = bench["failure_only"]
    assert (a["Q2"], a["Q3"], a["Q4"], a["Q5"]) == (bench["q2"], fo["q3"], fo["q4"], fo["q5"])
    assert a["rougeL"] == fo["q6"]["rougeL"] and a["auroc"] == bench["detection"]["auroc"]
    assert 0 < a["Q2"] < 100


def test_weighted_auroc_is_the_auroc_of_the_resample():
    """A record drawn k times weighs k: the same AUROC as the resample written out, ties and all."""
    from sklearn.metrics import roc_auc_score

    from labrobfail_vlm.bench.compare import auroc_row

    y = np.array([1, 0, 1, 0, 1, 0, 0, 1], bool)
    sa = np.array([0.9, 0.9, 0.4, 0.2, 0.4, 0.6, 0.1, 0.3])
    sb = np.array([0.5, 0.5, 0.5, 0.2, 0.7, 0.2, 0.6, 0.8])
    w = np.random.default_rng(0).integers(0, 3, (200, len(y))).astype(float)
    res = auroc_row(y, sa, sb, w)
    reps = [np.repeat(np.arange(len(y)), wt.astype(int)) for wt in w]
    diffs = [roc_auc_score(y[i], sb[i]) - roc_auc_score(y[i], sa[i]) for i in reps if 0 < y[i].sum() < len(i)]
    assert res["ci95"] == [round(float(np.percentile(diffs, q)), 4) for q in (2.5, 97.5)]
    assert res["diff"] == round(roc_auc_score(y, sb) - roc_auc_score(y, sa), 4) != 0


def test_bad_settings_are_one_line(tmp_path):
    recs = _dataset(tmp_path / "ds")
    for side in ("a", "b"):
        _write(tmp_path / side, recs, lambda t, d, r: r["conversations"][1]["value"], lambda t: 0.5)
    cases = {
        "seed=abc": "error: seed: expected a number",  # the command line's check, before the reader's
        "splits=3": "error: splits: expected a list",  # ("splits=val" is the list [val])
        "splits=[val,test_both]": "error: splits: test_both is a sealed split",
        f"out={tmp_path / 'no' / 'c.json'}": "error: out: no such folder",
        "splits=[val,val_both]": f"error: a: {tmp_path / 'a' / 'eval_val_both' / 'predictions.jsonl'} not found",
    }
    for arg, start in cases.items():
        r = compare(tmp_path, arg)
        assert r.returncode == 2 and r.stderr.startswith(start) and len(r.stderr.strip().splitlines()) == 1, r.stderr
    (tmp_path / "ds" / "val_both.json").write_text("[]")
    for side in ("a", "b"):
        _write(tmp_path / side, [], None, None, split="val_both")
    r = compare(tmp_path, "splits=[val_both]")
    assert r.returncode == 2 and r.stderr.strip() == f"error: splits: val_both has no records in {tmp_path / 'ds'}"
    traj = json.loads((tmp_path / "ds" / "trajectories.json").read_text())
    (tmp_path / "ds" / "trajectories.json").write_text(json.dumps(traj[1:]))
    r = compare(tmp_path)
    assert r.returncode == 2 and r.stderr.strip() == (
        "error: dataset_dir: trajectory p0-ok is asked about but not in trajectories.json"
    )
