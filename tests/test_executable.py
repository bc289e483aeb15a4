"""Executable correction accuracy: labrobfail-evaluate replays each failure, runs the correction, finishes."""

import json

from conftest import evaluate, run_here
from test_train import small_ds  # noqa: F401  (session fixture: a dataset built from conftest's run6 shards)


def test_gold_and_predicted_corrections_are_run_in_the_simulator(run6, small_ds, tmp_path):  # noqa: F811
    traj = {t["trajectory"]: t for t in json.loads((small_ds / "trajectories.json").read_text())}

    def failures(split):
        recs = json.loads((small_ds / f"{split}.json").read_text())
        return recs, [r for r in recs if r["id"].endswith("_Q6") and not traj[r["id"][:-3]]["success"]]

    split = next(s for s in ("test", "val", "train") if failures(s)[1])
    recs, failed = failures(split)
    assert failed, "the fixture split has a failure"
    # predictions: the gold answers, except one correction that maps to nothing
    preds = tmp_path / "preds.jsonl"
    lines = [{"id": r["id"], "prediction": r["conversations"][1]["value"]} for r in recs]
    for x in lines:
        if x["id"] == failed[0]["id"]:
            x["prediction"] = "Wipe the bench with a cloth."
    preds.write_text("".join(json.dumps(x) + "\n" for x in lines))
    out = tmp_path / "ev"
    r = evaluate(
        f"predictions={preds}",
        small_ds,
        f"split={split}",
        "executable.enabled=true",
        f"executable.shards={run6}",
        "progress=false",
        "baselines=[]",
        f"out_dir={out}",
        call=run_here,  # in this process: labrobfail-evaluate runs as one in test_faults.py
    )
    assert r.returncode == 0, r.stderr
    res = json.loads((out / "results.json").read_text())
    gold, model = res["q6_executable_gold"], res["q6_executable"]
    assert gold["failures"] == model["failures"] == len(failed)
    assert model["mapped"] == round(100.0 * (len(failed) - 1) / len(failed), 2) and gold["mapped"] == 100.0
    assert model["success"] <= gold["success"]
    assert "Executable correction accuracy" in (out / "results.md").read_text()


def test_executable_needs_the_shards(small_ds, tmp_path):  # noqa: F811
    preds = tmp_path / "p.jsonl"
    preds.write_text("")
    extra = ("executable.enabled=true", "progress=false", f"out_dir={tmp_path / 'o'}")
    r = evaluate(f"predictions={preds}", small_ds, *extra, call=run_here)
    assert r.returncode == 2 and "executable.shards: name the shard folder" in r.stderr
