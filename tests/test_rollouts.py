"""A policy's rollouts as training data: labrobfail-supervise shards=true, the dataset built from them, and
labrobfail-train extra_train, on real PyBullet episodes and real files."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import begin_episode, cli, run_here
from PIL import Image

from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.grid import GridConfig, sample_keyframes, whole_grid_picks


def test_a_grid_groups_a_policys_ticks_and_leaves_a_scripted_episode_as_it_was():
    segs = [0, 0, 1, 1, 1, 2, 2, 3, 3, 3, 4]
    distinct = [f"k{i}" for i in range(len(segs))]  # a scripted episode: no two keyframes in a row share a name
    assert whole_grid_picks(distinct, segs, 8) == sample_keyframes(segs, 8)
    # ticks named after the plan keyframe they head for: each name shown by its last tick
    names = ["a", "a", "a", "b", "b", "c", "d", "d", "e", "f", "g", "g", "h", "h", "i"]
    picks = whole_grid_picks(names, list(range(len(names))), 8)
    assert len(picks) == 8 and all(i == len(names) - 1 or names[i + 1] != names[i] for i in picks)
    # fewer names than cells: the cells are spread over the ticks themselves, not one cell per name
    assert len(whole_grid_picks(["a"] * 5 + ["b"] * 7, [0] * 12, 8)) == 8


def test_a_rollout_shard_builds_the_grid_the_supervisor_was_shown(tmp_path):
    """An episode of 'ticks' (each plan keyframe stepped twice, as a learned policy's ticks named after one plan
    keyframe are): the dataset built from its shard shows, pixel for pixel, the supervisor's final grid; only the
    images that grid shows are kept; the labels are the labeler's."""
    from labrobfail_data.cli import build_dataset as build_main
    from sim_backends.registry import make_backend
    from sim_backends.supervision.base import live_grid
    from sim_backends.supervision.rollouts import RolloutShards

    cfg = GridConfig(width=256, height=64, max_frames=8, columns=8)
    src = make_backend("pybullet", image_size=32, cameras=["front"], max_distractors=0)
    try:
        plan = begin_episode(src)
        for k in plan:
            src.step(k)
            src.step(dataclasses.replace(k, settle_steps=0))  # a second tick with the same name
        shown = live_grid(src, plan, cfg, final=True)
        ep = src.finish()
    finally:
        src.close()
    assert len(ep.executed_keyframes) == 2 * len(plan) and len(shown.keyframes) == 8
    assert all(k % 2 == 1 for k in shown.keyframes)  # each name's last tick
    sink = RolloutShards(tmp_path / "shards", 8, "act", "none")
    sink.add(ep, "place", 0)
    sink.close([{"labels": ep.labels.to_dict()}])

    import pyarrow.parquet as pq

    row = pq.read_table(tmp_path / "shards" / "shard-place-00000.parquet").to_pylist()[0]
    assert row["episode_id"] == "act-place-s0-none" and row["pair_id"] == "act-place-s0" and row["role"] == "rollout"
    assert [i for i, png in enumerate(row["images"][0]) if png] == shown.keyframes
    assert row["success"] == ep.labels.success and row["failure_type"] == ep.labels.failure_type
    assert json.loads((tmp_path / "shards" / "run.json").read_text())["render_frames"] == 8
    out = tmp_path / "ds"
    grid = ["grid.width=256", "grid.height=64", "grid.max_frames=8", "grid.columns=8", "progress=false"]
    assert build_main([f"shards={tmp_path / 'shards'}", f"out_dir={out}", *grid]) == 0
    built = np.asarray(Image.open(out / "images" / "seen-act-place-s0-none.png").convert("RGB"))
    assert np.array_equal(built, np.asarray(shown.image.convert("RGB")))
    with pytest.raises(ConfigError, match="render_frames=8"):  # another grid size is refused
        build_main([f"shards={tmp_path / 'shards'}", f"out_dir={tmp_path / 'ds4'}", "grid.max_frames=4"])


def test_an_unexplained_failure_is_left_out_and_a_family_with_goals_of_its_own_is_refused(tmp_path):
    from sim_backends.supervision.loop import TaskFamily
    from sim_backends.supervision.rollouts import RolloutShards, check_family
    from sim_backends.types import Labels

    sink = RolloutShards(tmp_path / "s", 8, "act", "none")
    ep = type("Ep", (), {"labels": Labels(False, evidence="unexplained: no detector fired")})()
    sink.add(ep, "pour", 0)  # type: ignore[arg-type]
    sink.close([{"labels": ep.labels.to_dict()}, {"labels": Labels(True).to_dict()}])
    assert json.loads((tmp_path / "s" / "run.json").read_text())["unexplained"] == 1
    assert not list((tmp_path / "s").glob("shard-*"))
    check_family(TaskFamily("pour", ["pour_beaker"]))
    with pytest.raises(ConfigError, match="shards: task 'pick' judges success by goals of its own"):
        check_family(TaskFamily("pick", ["pick_beaker"], steps=1, goals=[{"kind": "held"}]))


def _dataset(root, traj, grid):
    (root / "images").mkdir(parents=True)
    Image.new("RGB", (8, 8)).save(root / "images" / f"{traj}.png")
    rec = {"id": f"{traj}_Q2", "image": f"images/{traj}.png"}
    rec["conversations"] = [{"from": "human", "value": "<image>\nFailed?"}, {"from": "gpt", "value": "Yes"}]
    (root / "train.json").write_text(json.dumps([rec]))
    (root / "trajectories.json").write_text(json.dumps([{"trajectory": traj, "group": f"g-{traj}"}]))
    (root / "stats.json").write_text(json.dumps({"grid": grid}))


def test_extra_train_adds_another_datasets_records_with_their_own_images(tmp_path):
    from omegaconf import OmegaConf

    from labrobfail_vlm.train.cli import _check_dataset
    from labrobfail_vlm.train.data import VQADataset

    grid = {"width": 64, "max_frames": 4}
    _dataset(tmp_path / "a", "seen-ep1", grid)
    _dataset(tmp_path / "b", "seen-act-pour-s1-none", grid)
    ds = VQADataset(tmp_path / "a", "train", [tmp_path / "b"])
    assert len(ds) == 2 and ds.group_of == {t: f"g-{t}" for t in ("seen-ep1", "seen-act-pour-s1-none")}
    assert Image.open(ds[1]["image"]).size == (8, 8)
    assert Path(ds[1]["image"]).parent == (tmp_path / "b" / "images").resolve()
    with pytest.raises(ConfigError, match="extra_train: .* repeats 'seen-ep1_Q2'"):
        VQADataset(tmp_path / "a", "train", [tmp_path / "a"])
    _dataset(tmp_path / "c", "seen-other", {"width": 128, "max_frames": 4})
    run = OmegaConf.create({"dataset_dir": str(tmp_path / "a"), "grid_index": True, "extra_train": []})
    run.update(extra_repeat=1, packing=True, grounding={"weight": 0.0}, augment={"enabled": False})
    assert _check_dataset(run) == grid
    run.extra_train = [str(tmp_path / "b"), str(tmp_path / "c")]
    with pytest.raises(ConfigError, match="extra_train: .*c was built with grid"):
        _check_dataset(run)


def test_extra_repeat_draws_each_rollout_several_times_an_epoch_never_twice_in_one_pair_unit(tmp_path):
    from labrobfail_vlm.train.curriculum import PairSampler
    from labrobfail_vlm.train.packing import TrajectoryDataset

    grid = {"width": 64, "max_frames": 4}
    _dataset(tmp_path / "a", "seen-ep1", grid)
    _dataset(tmp_path / "b", "seen-act-pour-s1-none", grid)
    ds = TrajectoryDataset(tmp_path / "a", "train", [tmp_path / "b"], repeat=3)
    assert ds.ids() == ["seen-ep1_Q2"] + ["seen-act-pour-s1-none_Q2"] * 3
    assert len(TrajectoryDataset(tmp_path / "a", "train", [tmp_path / "b"])) == 2
    sampler = PairSampler(ds.ids(), ds.group_of, batch=4)
    assert sorted(map(len, sampler.units)) == [1, 1, 1, 1]  # three copies: three units, not one unit of three
    assert sorted(sampler) == [0, 1, 2, 3]


def test_a_resumed_rollout_run_adds_its_trials_shards_beside_the_first_runs(tmp_path):
    """shards=true, 1 trial, then the same command with 2: one shard per trial named after it, the manifest and
    run.json over both trials (the first not run again: its shard's bytes are the first run's)."""
    out = tmp_path / "run"
    argv = [cli("supervise"), "shards=true", "baseline=false", "supervisor=none", "task=pick_place_beaker_small"]
    argv += [f"out_dir={out}", "progress=false", "image_size=48", "cameras=[front]", "backend_kwargs.broken_glass=true"]
    assert run_here([*argv, "trials=1"]).returncode == 0
    d = out / "shards" / "none"
    first = {p.name: p.read_bytes() for p in d.glob("shard-*.parquet")}
    r = run_here([*argv, "trials=2"])
    assert r.returncode == 0, r.stderr
    shards = {p.name: p.read_bytes() for p in d.glob("shard-*.parquet")}
    unexplained = json.loads((d / "run.json").read_text())["unexplained"]
    assert set(shards) <= {"shard-pick_place_beaker_small-00000.parquet", "shard-pick_place_beaker_small-00001.parquet"}
    assert len(shards) + unexplained == 2 and all(shards[n] == b for n, b in first.items())
    assert json.loads((d / "manifest.json").read_text())["episodes"] == len(shards)
    from labrobfail_vlm.drawing import of_shards

    assert of_shards(d) == {"broken_glass": True, "button_lamp": False}  # what its grids drew, for a dataset of them


@pytest.mark.parametrize(
    "args, msg",
    [
        (["shard_frames=0"], "shard_frames: a positive number of grid frames, got 0"),
        (["shards=maybe"], "shards: expected true or false"),
        (["image_size=-1"], "image_size: expected an integer >= 1"),  # was a native bad_alloc
        ([], "holds trials of a run without run_config.json; give a new out_dir"),
    ],
)
def test_bad_rollout_settings_are_refused_before_a_trial_runs(tmp_path, args, msg):
    out = tmp_path / "run"
    (out / "shards" / "none").mkdir(parents=True)
    (out / "shards" / "none" / "shard-00000.parquet").write_bytes(b"an earlier run's")
    argv = [cli("supervise"), "shards=true", "baseline=false", "supervisor=none", f"out_dir={out}", *args]
    r = run_here([*argv, "progress=false", "trials=1"])
    assert r.returncode == 2 and msg in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not (out / "log.jsonl").exists()


@pytest.mark.parametrize(
    "args, msg",
    [
        (["extra_train={b}"], "extra_train: a list of dataset folders"),
        (["extra_train=[nowhere]"], "extra_train: 'nowhere' is not a dataset"),
        (["extra_train=[{b}]", "extra_repeat=2.5"], "extra_repeat: a positive integer"),
        (["extra_train=[{b}]", "extra_repeat=2", "packing=false"], "above 1 only with packing=true"),
        (["extra_train=[{b}]", "augment.enabled=true"], "extra_train: not with grounding.weight > 0 or augment"),
    ],
)
def test_bad_extra_train_settings_are_one_line_errors_before_a_model_is_made(tmp_path, args, msg):
    grid = {"width": 64, "max_frames": 4}
    _dataset(tmp_path / "a", "seen-ep1", grid)
    _dataset(tmp_path / "b", "seen-act-pour-s1-none", grid)
    args = [a.format(b=tmp_path / "b") for a in args]
    r = run_here(
        [cli("train"), "preset=tiny", f"dataset_dir={tmp_path / 'a'}", f"output_dir={tmp_path / 'out'}", *args]
    )
    assert r.returncode == 2 and msg in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not (tmp_path / "out").exists()
