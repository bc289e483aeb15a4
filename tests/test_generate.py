"""Generation into shards: manifest, HF datasets loading, resume after a kill, labels re-derived, bad config."""

import json
import signal
import time

import pytest
from conftest import ROOT, SMALL, SMALL_IMAGES, background, cli, gen, rows, run  # noqa: E402

from sim_backends.labeler import derive_labels
from sim_backends.types import Labels


def test_manifest_and_pairs(run6):
    man = json.loads((run6 / "manifest.json").read_text())
    assert man["episodes"] == 6 and man["pairs"] == 3
    for key in ("by_outcome", "by_category", "by_failure_type", "by_action", "by_horizon"):
        assert key in man
    assert len(man["by_failure_type"]) == 11
    # Redraws and left-out failures are counted; no label is a guess.
    assert man["guessed_labels"] == 0 and man["nominal_redraws"]["count"] >= 0 and man["left_out"]["count"] >= 0
    assert man["scenario_count"] == len({r["scenario"] for r in rows(run6)})
    rs = rows(run6)
    assert [r["role"] for r in rs] == ["nominal", "injected"] * 3
    for a, b in zip(rs[::2], rs[1::2]):
        assert a["pair_id"] == b["pair_id"] and a["seed"] == b["seed"] and a["scenario"] == b["scenario"]
        # Identical initial state: the first trace sample matches.
        ta, tb = json.loads(a["state_trace"]), json.loads(b["state_trace"])
        first = lambda t: {k: v[0] for k, v in t.items() if k not in ("kf_end", "rate_hz")}  # noqa: E731
        assert first(ta) == first(tb) and ta["rate_hz"] == tb["rate_hz"] > 0


def test_manifest_counts_physics_signs_and_gripper_faults_both_ways():
    """Real PyBullet episodes under the paper's draws: the manifest's injection summary shows delta of both signs per
    parameter and gripper faults in both directions, each labelled from state as a gripper control failure."""
    from conftest import SIGNS_AND_FAULTS, check_injection_summary, injected_rows

    from sim_backends import make_backend

    src = make_backend("pybullet", render=False)
    try:
        check_injection_summary(injected_rows(src, "pick_place_beaker_large", SIGNS_AND_FAULTS))
    finally:
        src.close()


def test_labels_rederived_from_recorded_state(run6):
    for r in rows(run6):
        lab = derive_labels(json.loads(r["state_trace"]), json.loads(r["task_meta"]))
        stored = Labels(
            r["success"], r["failure_type"], r["category"], r["severity"], r["failure_keyframe"], r["evidence"]
        )
        stored.onset_s = r["onset_s"]  # the onset's sim time, stored beside the labels
        assert lab == stored and (r["onset_s"] is None) == r["success"]


def test_loads_with_hf_datasets(run6):
    from datasets import load_dataset

    ds = load_dataset("parquet", data_files=sorted(str(p) for p in run6.glob("shard-*.parquet")), split="train")
    assert len(ds) == 6 and ds[0]["images"][0][0][:4] == b"\x89PNG"


def test_resume_after_sigkill_gives_identical_data(run6, tmp_path):
    out = tmp_path / "b"
    proc = background([cli("generate"), f"out_dir={out}", "num_episodes=6", "seed=5", *SMALL])
    deadline = time.time() + 300
    while time.time() < deadline and not list(out.glob("shard-*.parquet")):
        time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    (out / "shard-00002.parquet.tmp").write_bytes(b"truncated garbage")  # as a kill mid-write leaves it
    gen(out, "num_episodes=6", "seed=5")
    assert not list(out.glob("*.tmp"))
    a, b = rows(run6), rows(out)
    assert [r["episode_id"] for r in b] == [f"ep{i:07d}" for i in range(6)]
    assert [(r["state_trace"], r["images"], r["failure_type"]) for r in a] == [
        (r["state_trace"], r["images"], r["failure_type"]) for r in b
    ]


def test_first_pair_numbers_ids_and_seeds_so_a_second_run_adds_new_pairs(tmp_path):
    one = ["scenarios=[press_button_red]", "seed=5"]
    gen(tmp_path / "a", "num_episodes=6", *one)
    gen(tmp_path / "b", "num_episodes=2", "first_pair=2", *one)  # pair 2 of the same seed, alone
    a, b = rows(tmp_path / "a"), rows(tmp_path / "b")
    assert [(r["episode_id"], r["pair_id"]) for r in b] == [("ep0000004", "pair0000002"), ("ep0000005", "pair0000002")]
    assert [r["state_trace"] for r in b] == [r["state_trace"] for r in a[4:]]  # its seed follows the pair number
    assert a[0]["state_trace"] != b[0]["state_trace"]
    r = gen(tmp_path / "b", "num_episodes=2", *one, check=False)  # resuming with another numbering is refused
    assert r.returncode == 2 and "first_pair" in r.stderr


def test_reuse_from_copies_the_same_jobs_shards_and_refuses_another_run(run6, tmp_path):
    out = tmp_path / "half"
    r = gen(out, "num_episodes=4", "seed=5", f"reuse_from={run6}")  # run6's first two shards are this run's
    assert "copied 2 shard(s)" in r.stderr
    for name in ("shard-00000.parquet", "shard-00001.parquet", "shard-00000.rejects.json"):
        assert (out / name).read_bytes() == (run6 / name).read_bytes()
    assert [x["episode_id"] for x in rows(out)] == [f"ep{i:07d}" for i in range(4)]
    assert json.loads((out / "manifest.json").read_text())["episodes"] == 4
    r = gen(tmp_path / "other", "num_episodes=4", "seed=6", f"reuse_from={run6}", check=False)
    assert r.returncode == 2 and "Traceback" not in r.stderr and "reuse_from" in r.stderr and "seed" in r.stderr
    r = gen(tmp_path / "x", "num_episodes=2", f"reuse_from={tmp_path / 'nowhere'}", check=False)
    assert r.returncode == 2 and "reuse_from" in r.stderr and "run.json" in r.stderr


@pytest.mark.parametrize(
    "arg, field",
    [
        ("backend=gazebo", "backend"),
        ("num_episodes=-3", "num_episodes"),
        ("variant=unseen_moon", "variant"),
        ("scenarios=[fly_to_moon]", "scenarios"),
        ("workers=0", "workers"),
        ("first_pair=-1", "first_pair"),
        ("bogus_key=1", "bogus_key"),
        ("render_frames=0", "render_frames"),
        ("preset=moon", "preset"),
        ("backend_kwargs.custom_objects=tests/data/bad_objects.yaml", "backend_kwargs.custom_objects"),
        ("backend_kwargs.custom_scene=nowhere.yaml", "backend_kwargs.custom_scene"),
        ("backend_kwargs.custom_scene=tests/data/bad_vary_scene.yaml", "vary"),
        ("backend_kwargs.scene_family=moon", "scene_family"),
        ("backend_kwargs.object_colours=moon", "object_colours"),
        ("cameras=[front,moon]", "cameras"),  # was found by the renderer after run.json recorded it
        ("seed=abc", "seed"),  # likewise: the corrected rerun was then refused
        ("seed=[1]", "seed"),
        ("seed=4294967296", "seed"),  # 2**32: its seed words would be another (seed, pair)'s
        ("first_pair=4294967296", "first_pair"),
        ("reuse_from=REUSE_SELF", "reuse_from"),  # the out_dir itself
    ],
)
def test_bad_config_is_one_line(tmp_path, arg, field):
    arg = arg.replace("REUSE_SELF", str(tmp_path / "c"))
    r = gen(tmp_path / "c", "num_episodes=2", arg, check=False, here=arg != "backend=gazebo")  # the first: a process
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().count("\n") == 0 and field in r.stderr
    assert not (tmp_path / "c").exists()  # no folder, no run.json: the corrected command starts afresh


def test_unwritable_out_dir_and_nothing_lost(run6, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    r = gen(blocker / "sub", "num_episodes=2", check=False)
    assert r.returncode == 2 and "out_dir" in r.stderr and "Traceback" not in r.stderr
    before = {p.name: p.read_bytes() for p in run6.iterdir()}
    r = gen(run6, "num_episodes=6", "seed=4", check=False)  # a different run into a full dir is refused
    assert r.returncode == 2 and "seed" in r.stderr
    assert {p.name: p.read_bytes() for p in run6.iterdir()} == before


def test_a_nominal_plan_that_fails_is_redrawn_and_counted(tmp_path):
    """A scenario whose nominal plan can never succeed (a button out of reach): every draw is recorded and the
    pair is given up, so nothing unlabeled or mislabeled reaches a shard."""
    import yaml

    from sim_backends import make_backend
    from sim_backends.generate import MAX_DRAWS, labelable_pair
    from sim_backends.pybullet.backend import TASKS_FILE

    cfg = yaml.safe_load(TASKS_FILE.read_text())
    cfg["scenarios"] = {
        "press_out_of_reach": {"template": "press_button", "layout": {"button": {"kind": "button", "xy": [1.3, 0.0]}}}
    }
    tasks = tmp_path / "tasks.yaml"
    tasks.write_text(yaml.safe_dump(cfg))
    src = make_backend("pybullet", image_size=32, tasks_file=str(tasks), max_distractors=0)
    try:
        nominal, injected, records = labelable_pair(src, "press_out_of_reach", 0, 0, "seen")
    finally:
        src.close()
    assert nominal is None and injected is None
    kinds = [r["kind"] for r in records]
    assert kinds == ["nominal_redraw"] * MAX_DRAWS + ["given_up"]
    assert len({r["seed"] for r in records[:-1]}) == MAX_DRAWS  # each redraw is a new initial state
    assert all(r["evidence"] for r in records[:-1])


@pytest.mark.slow  # starts a Ray cluster
def test_ray_executor_gives_the_same_data(run6, tmp_path):
    """The paper-scale path: the same command on a (here local, 2-CPU) Ray instance writes the same shards as the
    process pool (run6): traces, labels and images. (It replaced a second Ray run that compared the traces alone.)"""
    pytest.importorskip("ray")
    out = tmp_path / "ray"
    gen(out, "num_episodes=6", "seed=5", "executor=ray", "workers=2")
    keys = ("episode_id", "scenario", "seed", "success", "failure_type", "failure_keyframe", "state_trace", "images")
    assert [[r[k] for k in keys] for r in rows(out)] == [[r[k] for k in keys] for r in rows(run6)]
    man = json.loads((out / "manifest.json").read_text())
    assert man["episodes"] == 6 and man["guessed_labels"] == 0


def test_render_frames_takes_only_the_images_its_grid_shows(tmp_path):
    """With render_frames=M an episode holds images at exactly the keyframes an M-frame grid samples (b"" at the
    others); the physics and labels are those of a fully rendered run; building another grid size is refused
    before anything is written, and a build with M frames works."""
    from labrobfail_vlm.grid import sample_keyframes

    full, part = tmp_path / "full", tmp_path / "part"
    gen(full, "num_episodes=2", "seed=5", "scenarios=[pick_place_bottle]")
    gen(part, "num_episodes=2", "seed=5", "scenarios=[pick_place_bottle]", "render_frames=4")
    for a, b in zip(rows(full), rows(part)):
        assert (a["state_trace"], a["failure_type"]) == (b["state_trace"], b["failure_type"])
        picks = sample_keyframes([k["segment"] for k in json.loads(b["keyframes"])], 4)
        assert len(b["images"][0]) > len(picks)
        for va, vb in zip(a["images"], b["images"]):
            assert [i for i, x in enumerate(vb) if x] == picks and all(vb[i] == va[i] for i in picks)
    build = [
        cli("build-dataset"),
        f"shards={part}",
        "grid.width=256",
        "grid.height=128",
        "grid.columns=4",
        "progress=false",
    ]
    r = run([*build, f"out_dir={tmp_path}/o8", "grid.max_frames=8"], 300)
    assert r.returncode == 2 and "render_frames=4" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "o8").exists()
    r = run([*build, f"out_dir={tmp_path}/o4", "grid.max_frames=4", "grid.columns=2"], 300)
    assert r.returncode == 0, r.stderr


def test_demo_preset_is_one_fixed_scene(tmp_path):
    """preset=demo (make demo's world) restricts the scenarios and fixes bench, light and cameras: the first frames
    of two pairs differ only where the objects stand; in the wide world the bench itself changes between them."""
    import io

    import numpy as np
    from PIL import Image

    def first_frames(out, *extra):
        r = run([cli("generate"), f"out_dir={out}", "num_episodes=4", *SMALL_IMAGES, *extra])
        assert r.returncode == 0, r.stderr
        rs = [x for x in rows(out) if x["role"] == "nominal"]
        assert len(rs) == 2, [x["role"] for x in rows(out)]
        return json.loads((out / "manifest.json").read_text()), [
            np.asarray(Image.open(io.BytesIO(x["images"][0][0])).convert("RGB"), dtype=int) for x in rs
        ]

    man, (a, b) = first_frames(tmp_path / "demo", "preset=demo")  # run in the repository: the bench file's path
    elsewhere = run(
        [cli("generate"), f"out_dir={tmp_path}/o", "preset=demo", "num_episodes=0", "progress=false"], 300, cwd=tmp_path
    )
    assert elsewhere.returncode == 0, elsewhere.stderr  # ... resolves from another directory too
    assert man["scenarios"] == ["pick_place_beaker_large", "pick_place_right_beaker_large"]
    _, (c, d) = first_frames(tmp_path / "wide", "scenarios=[pick_place_beaker_large,pick_place_right_beaker_large]")
    changed = lambda x, y: float((np.abs(x - y).max(axis=-1) > 12).mean())  # noqa: E731
    assert changed(a, b) < 0.25 and changed(c, d) > 0.5  # measured: 0.17 (the objects) and 0.98 (the bench)
    # `vary` in a scene file draws the named factors per episode again (the ladder between the two worlds)
    scene = tmp_path / "vary.yaml"
    scene.write_text((ROOT / "configs/scenes/demo_bench.yaml").read_text() + "vary: [bench, floor]\n")
    _, (e, f) = first_frames(tmp_path / "vary", "preset=demo", f"backend_kwargs.custom_scene={scene}")
    assert changed(e, f) > 0.5


def test_an_edited_scene_file_is_refused_on_resume(tmp_path):
    """run.json keeps the content of custom_scene, not only its path: editing the file and rerunning into the
    same out_dir would mix two benches in one dataset, so it is refused and nothing there changes."""
    scene = tmp_path / "bench.yaml"
    scene.write_text((ROOT / "configs/scenes/demo_bench.yaml").read_text())
    out = tmp_path / "o"
    args = ("num_episodes=0", "preset=demo", f"backend_kwargs.custom_scene={scene}")
    gen(out, *args)
    gen(out, *args)  # the same file again: a plain resume
    before = (out / "run.json").read_bytes()
    scene.write_text(scene.read_text().replace("bench:", "bench:\n  # edited\n", 1) + "checker: true\n")
    r = gen(out, *args, check=False)
    assert r.returncode == 2 and "Traceback" not in r.stderr and r.stderr.strip().count("\n") == 0
    assert "backend_kwargs.custom_scene" in r.stderr and "changed" in r.stderr
    assert (out / "run.json").read_bytes() == before


def test_demo_preset_on_another_backend_says_why(tmp_path):
    r = gen(tmp_path / "m", "num_episodes=0", "preset=demo", "backend=maniskill", check=False)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "preset=demo sets it" in r.stderr
