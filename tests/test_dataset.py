"""LabRobFail-Data: grids, six-dimension records, the filter, leak-free splits, exports, plots, paraphrase."""

import copy
import json
import os
import threading
from http.server import BaseHTTPRequestHandler, HTTPServer

import numpy as np
import pytest
from conftest import cli, gen, run, run_here
from PIL import Image

from labrobfail_data.annotate import check_record
from labrobfail_data.splits import assign
from labrobfail_vlm import questions as Q
from labrobfail_vlm.grid import BLANK, GridConfig, build_grid, frame_for_keyframe, sample_keyframes


def build(shards, out, *extra, here: bool = True, **kw):
    """labrobfail-build-dataset in this process (run_here), or as a process with here=False (`kw`: run's)."""
    argv = [cli("build-dataset"), f"shards={shards}", f"out_dir={out}", "progress=false", *extra]
    return run_here(argv) if here else run(argv, **kw)


@pytest.fixture(scope="module")
def held2(tmp_path_factory):
    out = tmp_path_factory.mktemp("gen") / "u"
    gen(out, "num_episodes=2", "seed=5", "variant=val_both")
    return out


@pytest.fixture(scope="module")
def ds(run6, held2, tmp_path_factory):
    out = tmp_path_factory.mktemp("ds") / "d"
    r = build(f"[{run6},{held2}]", out, here=False)
    assert r.returncode == 0, r.stderr
    return out


def load(ds, name):
    return json.loads((ds / f"{name}.json").read_text())


# ---- grid -------------------------------------------------------------------------------------------------
def frames(views=2, m=9, size=64):
    rng = np.random.default_rng(0)
    return [[rng.integers(0, 255, (size, size, 3), dtype=np.uint8) for _ in range(m)] for _ in range(views)]


def test_grid_layout_index_and_prefix():
    cfg = GridConfig()
    g = np.asarray(build_grid(frames(), cfg))
    assert g.shape == (768, 1536, 3)
    # time step 9 (index 8) wraps into the second band: row 2 (view 0), column 0
    assert g[384 + 96, 96].tolist() != list(BLANK)
    assert g[384 + 96, 192 + 96].tolist() == list(BLANK)  # time step 10 does not exist
    plain = np.asarray(build_grid(frames(), GridConfig(draw_index=False)))
    tag = (slice(0, 20), slice(0, 20))
    assert (g[tag] != plain[tag]).any() and (g[200:300, 50:150] == plain[200:300, 50:150]).all()
    prefix = np.asarray(build_grid(frames(), cfg, visible=3))
    assert (prefix[:384, 3 * 192 :] == BLANK).all() and (prefix[384:] == BLANK).all()
    assert (prefix[:384, : 3 * 192] == g[:384, : 3 * 192]).all()
    rows = np.asarray(build_grid(frames(), GridConfig(time_axis="rows")))
    assert rows.shape == (768, 1536, 3) and not (rows == g).all()
    with pytest.raises(ValueError, match="unequal"):
        build_grid([frames()[0], frames()[0][:3]])


def test_keyframe_sampling_keeps_action_transitions():
    segs = [0] * 10 + [1] * 12 + [2] * 13
    picks = sample_keyframes(segs, 16)
    assert len(picks) == 16 and picks == sorted(picks)
    assert {0, 9, 10, 21, 22, 34} <= set(picks)
    assert sample_keyframes([0, 0, 1], 16) == [0, 1, 2]
    assert frame_for_keyframe([0, 4, 9], 5) == 3 and frame_for_keyframe([0, 4, 9], 4) == 2


# ---- dataset ------------------------------------------------------------------------------------------------
def test_every_trajectory_has_six_dimensions_and_pairs_do_not_straddle(ds):
    traj = load(ds, "trajectories")
    recs = [r for s in ("train", "val", "test", "val_both") for r in load(ds, s)]
    by_traj = {}
    for r in recs:
        t, dim = r["id"].rsplit("_", 1)
        by_traj.setdefault(t, set()).add(dim)
        assert (ds / r["image"]).is_file()
    assert len(by_traj) == len(traj) == 8
    assert all(d == set(Q.DIMENSIONS) for d in by_traj.values())
    # every failure carries its onset (keyframe and sim time, from the trace); a success none
    for t in traj:
        if t["success"]:
            assert t["onset_keyframe"] is None and t["onset_s"] is None
        else:
            assert t["onset_keyframe"] == t["failure_keyframe"] and t["onset_s"] > 0, t
    split = {t["trajectory"]: t["split"] for t in traj}
    assert {split[t] for t in split if t.startswith("val_both")} == {"val_both"}
    pairs = {}
    for t in traj:
        pairs.setdefault(t["trajectory"].rsplit("-", 1)[0] + str(int(t["trajectory"][-7:]) // 2), set()).add(t["split"])
    assert all(len(s) == 1 for s in pairs.values())


def test_answers_follow_the_labels(ds):
    traj = {t["trajectory"]: t for t in load(ds, "trajectories")}
    recs = [r for s in ("train", "val", "test", "val_both") for r in load(ds, s)]
    for r in recs:
        t, dim = r["id"].rsplit("_", 1)
        info, q, a = traj[t], r["conversations"][0]["value"], r["conversations"][1]["value"]
        assert q.startswith("<image>\nThe image consists of a series of sequential frames.") and info["task"] in q
        if dim == "Q1":
            assert a == ", ".join(info["actions"])
        if dim == "Q3":
            assert a == (Q.NO_FAILURE if info["success"] else str(info["frame"]))
        if dim == "Q4" and not info["success"]:
            assert a == str(info["severity"]) and "(4) Management Incident" in q
        if dim == "Q5" and not info["success"]:
            assert a == str(info["category"]) and "(5) Safety Failure" in q
        if dim == "Q2":
            positive = "successfully" in q or "without issues" in q
            assert a == ("Yes" if positive == info["success"] else "No")


def test_exports_load_with_hf_datasets_and_stats_plots_exist(ds):
    import datasets

    d = datasets.load_dataset("json", data_files={"train": str(ds / "train.json")}, split="train")
    assert len(d) == len(load(ds, "train")) and set(d.column_names) >= {"id", "image", "conversations"}
    stats = load(ds, "stats")
    assert stats["filter"]["dropped_trajectories"] == 0 and stats["trajectories_kept"] == 8
    info = load(ds, "dataset_info")
    assert info["labrobfail_train"]["formatting"] == "sharegpt"
    for p in ("horizon_distribution", "success_failure_per_task", "failure_types_by_category"):
        im = Image.open(ds / "plots" / f"{p}.png")
        assert im.width > 300


def test_filter_rejects_bad_records(ds):
    traj = {t["trajectory"]: t for t in load(ds, "trajectories")}
    rec = next(r for r in load(ds, "train") if r["id"].endswith("_Q3") and not traj[r["id"][:-3]]["success"])
    info = traj[rec["id"][:-3]]
    assert check_record(rec, info) is None
    bad = copy.deepcopy(rec)
    bad["conversations"][1]["value"] = str(info["frames"] + 1)
    assert check_record(bad, info) == "frame_out_of_range"
    bad["conversations"][1]["value"] = str(info["frame"] % info["frames"] + 1)
    assert check_record(bad, info) == "inconsistent"
    assert check_record({"id": rec["id"], "conversations": []}, info) == "malformed"
    q2 = next(r for r in load(ds, "train") if r["id"] == rec["id"][:-3] + "_Q2")
    flipped = copy.deepcopy(q2)
    flipped["conversations"][1]["value"] = {"Yes": "No", "No": "Yes"}[q2["conversations"][1]["value"]]
    assert check_record(q2, info) is None and check_record(flipped, info) == "inconsistent"


def test_split_groups_are_exact_and_deterministic():
    held = [(f"{v}-pair0000000", v) for v in ("val_scene", "test_scene", "replay_test_scene")]
    groups = [(f"seen-pair{i:07d}", "seen") for i in range(50)] + held
    a = assign(groups, seed=1)
    assert a == assign(list(reversed(groups)), seed=1)
    counts = {s: list(a.values()).count(s) for s in ("train", "val", "test", "val_scene", "test_scene")}
    assert counts == {"train": 40, "val": 5, "test": 5, "val_scene": 1, "test_scene": 1}
    assert a["replay_test_scene-pair0000000"] == "replay_test_scene"  # a replay is never a val or test split
    with pytest.raises(ValueError, match="unknown variant"):
        assign([("x", "bogus")])


def test_bad_inputs_are_one_line_errors(run6, tmp_path):
    for args, field in [
        ([f"shards={tmp_path}/none"], "shards"),
        (["grid.time_axis=diagonal"], "grid.time_axis"),
        (["ratios=[0.5,0.5,0.5]"], "ratios"),
        (["bogus=1"], "bogus"),
        (["prefix.cuts=1", "prefix.pair_cuts=maybe"], "prefix.pair_cuts"),
        (["prefix.cuts=1", "prefix.questions=[Q2,Q3,Q4]"], "prefix.questions"),
        (["prefix.cuts=1", "prefix.questions=Q6"], "prefix.questions"),
        ([f"shards=[{run6},{run6}]"], "first_pair"),  # the same trajectories twice
        (["review_sample=-1"], "review_sample"),  # was found after the dataset had been rewritten
        (["paraphrase.enabled=true", "paraphrase.base_url=http://127.0.0.1:9/v1"], "paraphrase.base_url"),
        (["seed=[1,2]"], "seed"),
        (["grid.draw_index=maybe"], "grid.draw_index"),
        (["prefix.cuts=-1"], "prefix.cuts"),  # was taken as no cuts
    ]:
        shards = [f"shards={run6}"] if not args[0].startswith("shards") else []
        call = run if field == "shards" else run_here  # the first case as a real process, the rest in this one
        r = call([cli("build-dataset"), f"out_dir={tmp_path}/o", *shards, *args])
        assert r.returncode == 2 and "Traceback" not in r.stderr and field in r.stderr, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1
        assert not (tmp_path / "o").exists()  # refused before anything is written


def test_review_marks_remove_rejected(run6, ds, tmp_path):
    traj = load(ds, "trajectories")
    marks = {traj[0]["trajectory"]: "reject", traj[1]["trajectory"]: "accept"}
    (tmp_path / "m.json").write_text(json.dumps({"marks": marks}))
    r = build(run6, tmp_path / "o", f"review={tmp_path / 'm.json'}")
    assert r.returncode == 0, r.stderr
    stats = json.loads((tmp_path / "o" / "stats.json").read_text())
    assert stats["filter"]["by_reason"] == {"review_rejected": 1} and stats["trajectories_kept"] == 5
    (tmp_path / "bad.json").write_text("[1, 2]")
    r = build(run6, tmp_path / "o2", f"review={tmp_path / 'bad.json'}")
    assert r.returncode == 2 and "review" in r.stderr


class _FakeLLM(BaseHTTPRequestHandler):
    seen_auth: list = []
    seeds: list = []
    mode = "good"

    def do_POST(self):  # noqa: N802
        body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
        _FakeLLM.seen_auth.append(self.headers.get("Authorization"))
        _FakeLLM.seeds.append(body.get("seed"))
        payload = json.loads(body["messages"][1]["content"])
        if _FakeLLM.mode == "good":
            out = {"question": "Rephrased: " + payload["question"], "answer": payload.get("answer")}
        else:  # a reply that changes the meaning: the filter must catch it
            out = {"question": payload["question"], "answer": "Do something else entirely please."}
        reply = {"choices": [{"message": {"content": json.dumps(out)}}]}
        data = json.dumps(reply).encode()
        self.send_response(200)
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    def log_message(self, *a):
        pass


@pytest.mark.parametrize("mode", ["good", "bad"])
def test_paraphrase_through_openai_compatible_endpoint(run6, tmp_path, mode):
    srv = HTTPServer(("127.0.0.1", 0), _FakeLLM)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    _FakeLLM.mode, _FakeLLM.seen_auth, _FakeLLM.seeds = mode, [], []
    env = {**os.environ, "LRF_TEST_KEY": "sk-secret-123"}
    out = tmp_path / "p"
    url = f"http://127.0.0.1:{srv.server_port}/v1"
    paraphrase = ["paraphrase.enabled=true", f"paraphrase.base_url={url}", "paraphrase.api_key_env=LRF_TEST_KEY"]
    r = build(run6, out, *paraphrase, here=False, timeout=300, env=env)  # the key from a process's environment
    asked = len(_FakeLLM.seeds)
    para = json.loads((out / "stats.json").read_text())["paraphrase"]
    assert asked == para.get("accepted", 0) + para.get("rejected", 0)  # one request per record, none shared
    assert all(isinstance(x, int) for x in _FakeLLM.seeds) and len(set(_FakeLLM.seeds)) == asked
    if mode == "good":  # a rebuild reuses the kept replies: no request, the same records
        first = (out / "train.json").read_bytes()
        assert build(run6, out, *paraphrase).returncode == 0
        assert len(_FakeLLM.seeds) == asked and (out / "train.json").read_bytes() == first
    srv.shutdown()
    assert r.returncode == 0, r.stderr
    assert _FakeLLM.seen_auth and set(_FakeLLM.seen_auth) == {"Bearer sk-secret-123"}
    stats = json.loads((out / "stats.json").read_text())
    text = "".join(p.read_text() for p in out.glob("*.json")) + (out / "review.html").read_text() + r.stdout + r.stderr
    assert "sk-secret-123" not in text
    if mode == "good":
        assert stats["paraphrase"]["accepted"] > 0 and "Rephrased: " in text
    else:  # Q6 answers that lose the object names are rejected; the originals stay
        assert stats["paraphrase"].get("rejected", 0) > 0 and stats["trajectories_kept"] == 6


def test_pair_cuts_cut_twins_at_the_same_keyframes(run6, tmp_path):
    """prefix.pair_cuts: a pair's twins get the same prefix lengths (placed around the failed twin's frame), each
    prefix keeps its own trajectory's answer, and the whole-grid records do not change."""
    grid = ["grid.width=256", "grid.height=128", "grid.max_frames=8", "grid.columns=4"]
    on, off = tmp_path / "on", tmp_path / "off"
    assert build(run6, on, "prefix.cuts=2", "prefix.pair_cuts=true", *grid).returncode == 0
    assert build(run6, off, "prefix.cuts=2", *grid).returncode == 0
    traj = {t["trajectory"]: t for t in load(on, "trajectories")}
    cuts: dict[str, dict[str, list[int]]] = {}
    for t in traj.values():
        if "prefix_of" in t:
            cuts.setdefault(t["group"], {}).setdefault(t["prefix_of"], []).append(t["visible"])
    shared = 0
    for pair in cuts.values():
        if len(pair) == 2:
            (a, ka), (b, kb) = pair.items()
            if traj[a]["frames"] == traj[b]["frames"]:  # twins of different lengths have different cut ranges
                assert ka == kb, (a, ka, b, kb)
                shared += 1
    assert shared >= 1
    for t in traj.values():  # each prefix's answer is its own trajectory's: failed yet iff its frame <= k
        if "prefix_of" in t:
            full = traj[t["prefix_of"]]
            assert t["success"] == (full["frame"] is None or full["frame"] > t["visible"])
    rec_on = [x for x in load(on, "train") if "-p" not in Q.traj_of(x["id"])]
    assert rec_on == [x for x in load(off, "train") if "-p" not in Q.traj_of(x["id"])]
    assert load(on, "test") == load(off, "test")
    assert json.loads((on / "stats.json").read_text())["prefix"]["pair_cuts"] is True


def test_trace_until_is_the_state_when_a_keyframe_ended():
    """A prefix's correction reads the trace as it stood at the cut: a beaker that falls later has not fallen."""
    from sim_backends.goals import object_fell
    from sim_backends.schema import trace_until

    z = [0.8] * 7 + [0.1] * 3  # knocked off the bench during the third keyframe
    trace = {
        "t": [i / 40 for i in range(10)],
        "kf_end": [2, 5, 9],
        "rate_hz": 40.0,
        "beaker.pos": [[0.0, 0.0, h] for h in z],
        "beaker.quat": [[0.0, 0.0, 0.0, 1.0]] * 10,
    }
    meta = {"objects": {"beaker": {"kind": "vessel"}}, "bench_top": 0.75}
    assert object_fell(trace, meta) and not object_fell(trace_until(trace, 1), meta)
    cut = trace_until(trace, 1)
    assert cut["kf_end"] == [2, 5] and len(cut["t"]) == len(cut["beaker.pos"]) == 6 and cut["rate_hz"] == 40.0
    assert trace_until(trace, 2) == trace


def test_prefix_records_follow_the_failure_frame(run6, ds, tmp_path):
    from labrobfail_data.annotate import prefix_cut_points
    from labrobfail_vlm.analyzer import nearest_strategy

    out = tmp_path / "p"
    r = build(
        run6,
        out,
        "prefix.cuts=2",
        "prefix.questions=[Q2,Q3,Q5,Q6]",
        "grid.width=256",
        "grid.height=128",
        "grid.max_frames=8",
        "grid.columns=4",
    )
    assert r.returncode == 0, r.stderr
    traj = {t["trajectory"]: t for t in load(out, "trajectories")}
    prefixes = [t for t in traj.values() if "prefix_of" in t]
    assert prefixes and all(t["visible"] < traj[t["prefix_of"]]["frames"] for t in prefixes)
    recs = load(out, "train") + sum(
        (load(out, f"{s}_prefix") for s in ("val", "test") if (out / f"{s}_prefix.json").is_file()), []
    )
    seen_before = seen_after = 0
    dims: dict[str, list[str]] = {}
    for rec in recs:
        t = traj[Q.traj_of(rec["id"])]
        if "prefix_of" not in t:
            continue
        full = traj[t["prefix_of"]]
        failed_yet = full["frame"] is not None and full["frame"] <= t["visible"]
        seen_before += full["frame"] is not None and not failed_yet
        seen_after += failed_yet
        ans = rec["conversations"][1]["value"]
        dim = Q.dim_of(rec["id"])
        dims.setdefault(t["trajectory"], []).append(dim)
        if dim == "Q2":
            assert ans == Q.q2_answer(Q.q2_variant(rec["conversations"][0]["value"]), not failed_yet)
        elif dim == "Q3":
            assert ans == (str(full["frame"]) if failed_yet else Q.NO_FAILURE)
        elif dim == "Q5":
            assert ans == (str(full["category"]) if failed_yet else Q.NO_FAILURE)
        else:  # Q6: the prefix's own strategy, the trajectory's unless an object fell after the cut (then manual)
            assert dim == "Q6" and (nearest_strategy(ans) == t["strategy"] if failed_yet else ans == Q.NO_CORRECTION)
            assert not failed_yet or full["strategy"] == "MANUAL" or t["strategy"] == full["strategy"]
        assert check_record(rec, t) is None
    assert seen_before and seen_after  # a failure gets cuts both before and at/after its frame
    assert set(map(tuple, dims.values())) == {("Q2", "Q3", "Q5", "Q6")}
    assert json.loads((out / "stats.json").read_text())["prefix"]["questions"] == ["Q2", "Q3", "Q5", "Q6"]
    # the first hidden time step is blank in every view, the last shown one is not
    g = GridConfig(width=256, height=128, max_frames=8, columns=4)
    for t in prefixes[:6]:
        img = np.asarray(Image.open(out / "images" / f"{t['trajectory']}.png"))
        rows, cols = g.shape(2)
        h, w = 128 // rows, 256 // cols
        for k in range(2):
            r_, c_ = g.cell(t["visible"], k, 2)
            assert (img[r_ * h : (r_ + 1) * h, c_ * w : (c_ + 1) * w] == BLANK[0]).all()
            r_, c_ = g.cell(t["visible"] - 1, k, 2)
            assert not (img[r_ * h : (r_ + 1) * h, c_ * w : (c_ + 1) * w] == BLANK[0]).all()
    # the main records are the same with and without prefixes; evaluation prefixes stay out of test.json
    base = tmp_path / "b"
    assert build(run6, base, "grid.width=256", "grid.height=128", "grid.max_frames=8", "grid.columns=4").returncode == 0
    assert load(base, "test") == load(out, "test")
    assert [x for x in load(out, "train") if "-p" not in Q.traj_of(x["id"])] == load(base, "train")
    # cut points: in range, distinct, both sides of the failure frame first
    rng = np.random.default_rng(0)
    for _ in range(20):
        cuts = prefix_cut_points(8, 5, 2, rng)
        assert len(cuts) == 2 and cuts[0] < 5 <= cuts[1]
    assert prefix_cut_points(1, None, 2, rng) == []


def test_without_drawn_labels_no_prompt_mentions_them(run6, tmp_path):
    """The paper's "w/o temporal index" ablation: no label on the grid, and no question pointing at one."""
    recs = {}
    for name, extra in (("noidx", ["grid.draw_index=false"]), ("idx", [])):
        r = build(run6, tmp_path / name, *extra)
        assert r.returncode == 0, r.stderr
        recs[name] = [
            x["conversations"][0]["value"] for s in ("train", "val", "test") for x in load(tmp_path / name, s)
        ]
    assert json.loads((tmp_path / "noidx" / "stats.json").read_text())["grid"]["draw_index"] is False
    for q in recs["noidx"]:
        assert not any(w in q.lower() for w in ("label", "upper left", "top-left", "indices", "displayed")), q
    assert recs["idx"] and all("top-left corner" in q for q in recs["idx"])
