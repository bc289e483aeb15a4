"""scripts/recall_by_miss.py: which goals a failure failed, how far an "at" goal missed, the pixels it makes, and
recall counted as the bench counts it, on a real generated run."""

import json

import pybullet as p
from conftest import cli, program, run_here

from labrobfail_vlm import questions as Q
from labrobfail_vlm.bench.evaluate import q2_as_asked
from scripts.recall_by_miss import at_miss, pixel_offsets, summarise

META = {
    "places": {"mark": [0.0, 0.0, 0.0]},
    "bench_top": 0.0,
    "goals": [{"kind": "at", "object": "cup", "xy": "mark", "tol": 0.04}, {"kind": "upright", "object": "cup"}],
}


def trace_at(x: float, quat=(0.0, 0.0, 0.0, 1.0), z: float = 0.02) -> dict:
    return {"cup.pos": [[0.5, 0.5, 0.1], [x, 0.0, z]], "cup.quat": [list(quat), list(quat)]}


def test_at_miss_reads_the_final_state():
    assert at_miss(trace_at(0.1), META)[:2] == (["at"], 0.1)
    assert at_miss(trace_at(0.03), META)[:2] == ([], None)  # within the goal's tolerance
    tipped = p.getQuaternionFromEuler([1.0, 0.0, 0.0])
    assert at_miss(trace_at(0.0, tipped), META)[:2] == (["upright"], None)  # on its mark, lying down
    kinds, miss, goal = at_miss(trace_at(-0.2, tipped), META)
    assert kinds == ["at", "upright"] and abs(miss - 0.2) < 1e-9 and goal["xy"] == "mark"
    kinds, miss, goal = at_miss(trace_at(0.01, z=-0.2), META)  # on its mark's x-y, under the bench top
    assert kinds == ["at"] and miss <= goal["tol"]
    tube = {**META, "goals": [{"kind": "at", "object": "cup", "xy": "mark", "tol": 0.012}]}  # a goal's own tolerance
    assert at_miss(trace_at(0.03), tube)[:2] == (["at"], 0.03)


def test_pixel_offsets_grow_with_the_miss_and_skip_a_camera_looking_away():
    toward = p.computeViewMatrix([0.0, -1.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    away = p.computeViewMatrix([0.0, -1.0, 1.0], [0.0, -2.0, 1.0], [0.0, 0.0, 1.0])
    proj = p.computeProjectionMatrixFOV(60, 1.0, 0.01, 5.0)
    cams = json.dumps([[list(toward) + list(proj)], [None, list(away) + list(proj)]])
    row = {"camera_names": ["front", "side"], "cameras": cams}
    goal = META["goals"][0]
    near, far = (pixel_offsets(row, trace_at(x), META, goal, 128) for x in (0.05, 0.2))
    assert set(near) == {"front"} and 0 < near["front"] < far["front"]


def item(miss, caught, tol=0.04, kinds=("at",), height=False, px=None):
    return {
        "type": "a",
        "kinds": list(kinds),
        "miss_m": miss,
        "tol_m": tol,
        "height_only": height,
        "caught": caught,
        "offset_px": px or {},
    }


def test_summary_bins_at_only_failures_by_miss_per_tolerance():
    items = [
        item(0.05, False, px={"front": 6.0}),
        item(0.3, True, px={"front": 40.0}),
        item(0.03, True, tol=0.012),  # a tube 3 cm beside its hole: under the first edge, in its own group
        item(0.01, False, height=True),  # an "at" goal failed on height alone: in no miss bin
        item(0.3, True, kinds=("at", "upright")),
    ]
    s = summarise(items, [0.04, 0.1])
    assert s["by_failed_goals"] == {
        "at only": {"n": 3, "caught": 2},
        "at only, on height": {"n": 1, "caught": 0},
        "other goals": {"n": 1, "caught": 1},
    }
    bins = {tol: [(b["miss_m"], b["n"], b["caught"]) for b in bs] for tol, bs in s["at_only_by_miss"].items()}
    assert bins == {
        "0.012": [([0.0, 0.04], 1, 1), ([0.04, 0.1], 0, 0), ([0.1, None], 0, 0)],
        "0.04": [([0.0, 0.04], 0, 0), ([0.04, 0.1], 1, 0), ([0.1, None], 1, 1)],
    }
    assert s["at_only_by_miss"]["0.04"][2]["median_offset_px"] == {"front": 40.0}


def test_counts_recall_as_the_bench_does_on_a_generated_run(run6, tmp_path):
    (tmp_path / "shards").mkdir()
    (tmp_path / "shards" / "seen").symlink_to(run6)
    r = run_here([cli("build-dataset"), f"shards={run6}", f"out_dir={tmp_path / 'dataset'}", "progress=false"])
    assert r.returncode == 0, r.stderr
    traj = {t["trajectory"]: t for t in json.loads((tmp_path / "dataset" / "trajectories.json").read_text())}
    split = "train"  # three pairs: the one split that surely holds failures
    q2 = [r for r in json.loads((tmp_path / "dataset" / f"{split}.json").read_text()) if Q.dim_of(r["id"]) == "Q2"]
    failed = {Q.traj_of(r["id"]) for r in q2 if not traj[Q.traj_of(r["id"])]["success"]}
    assert failed
    bench = tmp_path / f"eval_{split}"
    bench.mkdir()
    called = set(sorted(failed)[::2]) | {Q.traj_of(r["id"]) for r in q2} - failed  # half the failures, every success
    for says, caught in ((lambda t: t in called, len(failed & called)), (lambda t: False, 0)):
        lines = [
            {"id": r["id"], "prediction": q2_as_asked(r["conversations"][0]["value"], says(Q.traj_of(r["id"])))}
            for r in q2
        ]
        (bench / "predictions.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
        r = run_here(program("scripts/recall_by_miss.py") + [f"run={tmp_path}", f"bench={bench}", f"split={split}"])
        assert r.returncode == 0, r.stderr
        out = json.loads((bench / "recall_by_miss.json").read_text())
        assert (out["failures"], out["caught"]) == (len(failed), caught)
        assert {it["trajectory"] for it in out["trajectories"]} == failed
    script = program("scripts/recall_by_miss.py") + [f"run={tmp_path}"]
    for args, named in (
        ([f"split={split}"], "bench:"),
        ([f"bench={bench}", "split=test_both"], "sealed"),
        ([f"bench={bench}", f"split={split}", "edges=0.05"], "edges:"),
    ):
        bad = run_here(script + args)
        assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and named in bad.stderr, bad.stderr
    (tmp_path / "shards" / "seen_again").symlink_to(run6)  # the same episodes in a second folder: which is meant?
    bad = run_here(script + [f"bench={bench}", f"split={split}"])
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "two shard folders" in bad.stderr, bad.stderr
