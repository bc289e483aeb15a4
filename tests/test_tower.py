"""The sim-pretrained vision tower: targets from simulator state, a real tiny pretraining run that resumes and
exports, the tower loaded into the tiny Qwen3-VL (and the scratch path), the shipped tower's card, bad input."""

import json
import shutil
import sys

import numpy as np
import pytest
from conftest import cli, gen, run, run_here

# 4 keyframes x 2 views of 64 px in square 64 px cells (2 x 2 merged tokens each)
TOWER_GRID = ["grid.width=128", "grid.height=256", "grid.max_frames=4", "grid.columns=2"]
TINY_TOWER = ["vision.depth=1", "vision.hidden_size=32", "vision.intermediate_size=64", "vision.num_heads=2"]


@pytest.fixture(scope="module")
def tower_shards(tmp_path_factory):
    out = tmp_path_factory.mktemp("tower") / "shards"
    gen(out, "num_episodes=6", "seed=5", "image_size=64", "render_frames=4", "backend_kwargs.wrist=true")
    return out


@pytest.fixture(scope="module")
def tower_data(tower_shards, tmp_path_factory):
    out = tmp_path_factory.mktemp("tower") / "data"
    frames = ["data.max_frames=4", "data.image_size=64", "data.ratios=[0.6,0.4]", "data.progress=false"]
    r = run([cli("build-tower-data"), f"data.shards={tower_shards}", f"data.out_dir={out}", *frames], 300)
    assert r.returncode == 0, r.stderr
    return out


def _pretrain(data, out, *extra, here: bool = False):
    """labrobfail-pretrain-tower on `data`, as a process (or in this one: run_here)."""
    tower = [*TOWER_GRID, *TINY_TOWER, "batch_size=2", "progress=false"]
    argv = [cli("pretrain-tower"), f"data.out_dir={data}", f"out_dir={out}", *tower, *extra]
    return run_here(argv) if here else run(argv)


def test_targets_come_from_simulator_state(tower_shards):
    import pyarrow.parquet as pq

    from labrobfail_data.annotate import grid_failure_frame, grid_picks
    from labrobfail_data.frame_targets import CELL_TARGETS, row_targets

    rows = [r for f in sorted(tower_shards.glob("shard-*.parquet")) for r in pq.read_table(f).to_pylist()]
    assert {r["success"] for r in rows} == {True, False}
    for r in rows:
        picks = grid_picks(r, 4)
        frame = grid_failure_frame(r, picks)
        cells, points = row_targets(r, picks, range(3), frame, 64)
        fb = cells[:, 0, CELL_TARGETS.index("failed_by_now")]
        goals = cells[-1, 0, CELL_TARGETS.index("goals_hold")]
        if r["success"]:
            assert goals == 1 and not fb.any()  # every goal holds at the end of a success, and it never failed
        else:
            assert goals == 0 and fb[frame - 1 :].all() and not fb[: frame - 1].any()
        assert (cells[:, 0] == cells[:, 1]).all()  # the state is one per frame, whatever the view
        assert cells[0, 0, CELL_TARGETS.index("arm_moved")] == -1  # nothing to compare the first frame with
        # the gripper is somewhere in front of every camera: a finite projection in every view
        assert np.isfinite(points[:, :, 0, 0]).all()


def test_pretraining_resumes_exports_and_the_tiny_model_takes_the_tower(tower_data, tmp_path):
    run = tmp_path / "run"
    r = _pretrain(tower_data, run, "epochs=1", "layouts=[[front,side],[front,wrist]]", here=True)
    assert r.returncode == 0, r.stderr[-3000:]
    r = _pretrain(
        tower_data, run, "epochs=2", "layouts=[[front,side],[front,wrist]]", f"export_dir={tmp_path / 'x'}", here=True
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert "resuming after epoch 1" in r.stderr
    metrics = json.loads((run / "metrics.json").read_text())
    assert [m["epoch"] for m in metrics] == [1, 2] and all(m["loss_cell"] > 0 for m in metrics)
    before = {f.name: f.read_bytes() for f in (run / "checkpoint").iterdir()}
    for change in ("augment.raise_saturation=true", "lr=5e-4"):  # a run is not continued under other settings
        r = _pretrain(tower_data, run, "epochs=3", "layouts=[[front,side],[front,wrist]]", change, here=True)
        assert r.returncode == 2 and "Traceback" not in r.stderr and r.stderr.strip().count("\n") == 0
        assert r.stderr.startswith(f"error: {change.partition('=')[0]}:")
    assert {f.name: f.read_bytes() for f in (run / "checkpoint").iterdir()} == before
    card = json.loads((tmp_path / "x" / "tower.json").read_text())
    assert card["vision_config"]["depth"] == 1 and set(card["heldout"]) == {"front+side", "front+wrist"}
    seen = card["heldout"]["front+side"]["seen"]
    assert "failed_by_now" in seen["cells"] and "gripper" in seen["tokens"]
    assert (tmp_path / "x" / "TOWER_CARD.md").read_text().startswith("# The LabRobFail vision tower")
    assert "(seen, seed 5)" in card["data_summary"]  # the card says how its frames were generated

    import torch
    from safetensors.torch import load_file

    from labrobfail_vlm.model.loading import load_model
    from labrobfail_vlm.model.tiny import build_tiny
    from labrobfail_vlm.model.tower import raised_saturation, read_card
    from labrobfail_vlm.train.tower_card import augment_line

    read_card(tmp_path / "x")  # the sha256 on the card is the file's
    m = load_model(build_tiny(tmp_path / "tiny", tower=tmp_path / "x"))
    want = load_file(str(tmp_path / "x" / "tower.safetensors"))
    got = m.model.visual.state_dict()
    assert want.keys() == got.keys() and all(torch.equal(want[k], got[k]) for k in want)
    scratch = load_model(build_tiny(tmp_path / "scratch")).model.visual.state_dict()
    assert not torch.equal(scratch["blocks.0.attn.qkv.weight"][:4, :4], want["blocks.0.attn.qkv.weight"][:4, :4])
    # a run started from that tower (init=), all hues, a vanishing learning rate: it exports the tower it started from
    r = _pretrain(
        tower_data,
        tmp_path / "run2",
        "epochs=1",
        "layouts=[[front,side]]",
        f"init={tmp_path / 'x'}",
        "lr=1e-12",
        "augment.hue=0.5",
        f"export_dir={tmp_path / 'y'}",
        here=True,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    again = load_file(str(tmp_path / "y" / "tower.safetensors"))
    assert all(torch.allclose(want[k], again[k], atol=1e-6) for k in want)
    card = json.loads((tmp_path / "y" / "tower.json").read_text())
    assert card["training"]["init"] == str(tmp_path / "x") and card["training"]["augment"]["hue"] == 0.5
    assert card["training"]["init_sha256"] == read_card(tmp_path / "x")["sha256"]
    assert card["training"]["init_sha256"] in (tmp_path / "y" / "TOWER_CARD.md").read_text()
    assert card["training"]["augment"]["raise_saturation"] is False  # configs/tower.yaml's, said on the card:
    assert "hue turned up to 0.5 turn; no pixel's saturation raised" in (tmp_path / "y" / "TOWER_CARD.md").read_text()
    assert augment_line({}) == "Augmentation: not recorded on this card."
    # what a page may say of the sealed colours, read from the card of the tower its run started from
    y = {"path": str(tmp_path / "y"), "sha256": card["sha256"]}
    assert raised_saturation(y) is False and raised_saturation(None) is False  # kept; a random tower
    assert raised_saturation({**y, "sha256": "0" * 64}) is True  # another tower at that path now: not known
    (tmp_path / "z").mkdir()
    shutil.copyfile(tmp_path / "y" / "tower.safetensors", tmp_path / "z" / "tower.safetensors")  # the card's weights
    older = {"colour": 0.75, "shift_px": 8, "scale": 0.1, "hue": 0.5}  # the tower shipped until 6 Dec: no key
    for aug in ({**card["training"]["augment"], "raise_saturation": True}, older):
        (tmp_path / "z" / "tower.json").write_text(json.dumps({**card, "training": {"augment": aug}}))
        assert raised_saturation({**y, "path": str(tmp_path / "z")}) is True  # raising, or a card older than the key
    # a damaged tower is refused in one line, before any model is built
    (tmp_path / "x" / "tower.safetensors").write_bytes(b"\0" * 64)
    with pytest.raises(Exception, match="does not match the sha256"):
        read_card(tmp_path / "x")


def test_train_takes_a_tower_or_scratch(tower_shards, tower_data, tmp_path):
    pretrained = tmp_path / "run"
    r = _pretrain(tower_data, pretrained, "epochs=1", "layouts=[[front,side]]")
    assert r.returncode == 0, r.stderr[-3000:]
    ds = tmp_path / "ds"
    two_views = ["views=[front,side]", *TOWER_GRID, "progress=false"]
    r = run([cli("build-dataset"), f"shards={tower_shards}", f"out_dir={ds}", *two_views], 300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads((ds / "stats.json").read_text())["views"] == ["front", "side"]
    common = [
        sys.executable,
        "train.py",
        "preset=tiny",
        f"dataset_dir={ds}",
        "max_steps=1",
        "global_batch=2",
        "per_device_batch=2",
        "grounding.pretrain_epochs=0",
        "wandb.enabled=false",
        "progress=false",
        "augment.enabled=true",
    ]
    for tower in (str(pretrained), "scratch"):
        out = tmp_path / f"t-{tower == 'scratch'}"
        r = run_here([*common, f"output_dir={out}", f"tower={tower}"])
        assert r.returncode == 0, r.stderr[-3000:]
        cfg = json.loads((out / "tiny_base" / "config.json").read_text())["vision_config"]
        assert (cfg["depth"], cfg["hidden_size"]) == ((1, 32) if tower != "scratch" else (2, 64))
    r = run_here([*common, f"output_dir={tmp_path / 'bad'}", f"tower={tmp_path / 'none'}"])
    assert r.returncode == 2 and r.stderr.strip().splitlines()[-1].startswith("error: tower:"), r.stderr


def test_bad_tower_settings_are_one_line(tower_data, tmp_path):
    for args, key in (
        (["epochs=0"], "epochs"),
        (["lr=-1"], "lr"),
        (["layouts=[[front,side],[front]]"], "layouts"),
        (["layouts=front"], "layouts"),  # was read as a one-view layout of five letters
        (["vision.depth=-1"], "vision.depth"),  # was a tower exported with depth -1
        (["layouts=[[front,top]]"], "layouts"),  # a view no trajectory has: was found after an epoch's checkpoint
        ([f"data.out_dir={tmp_path}"], "data"),
        (["grid.width=100"], "grid"),
        ([f"init={tmp_path / 'none'}"], "tower"),
        (["augment.hue=0.7"], "augment"),
        (["augment.colour=strong"], "augment.colour"),
        (["augment.raise_saturation=maybe"], "augment.raise_saturation"),
    ):
        r = _pretrain(tower_data, tmp_path / "r", *args, here=key != "epochs")  # the first case as a process
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-2000:]
        assert r.stderr.strip().splitlines()[-1].startswith(f"error: {key}"), r.stderr
        assert not (tmp_path / "r").exists() or key != "layouts"  # refused before its folder is made


def test_hue_range_reaches_any_hue_and_the_default_draw_is_unchanged():
    import cv2

    from labrobfail_vlm.augment import Augment, AugmentConfig

    def hues(cfg, n=200):
        rng = np.random.default_rng(0)
        patch = np.full((8, 8, 3), (178, 224, 242), np.uint8)  # the seen small beaker's pale blue
        out = []
        for _ in range(n):
            img = Augment.draw(cfg, 1, rng).image(patch, 0)
            out.append(int(cv2.cvtColor(img, cv2.COLOR_RGB2HSV)[4, 4, 0]))
        return np.array(out)

    base = hues(AugmentConfig(colour=0.25, shift_px=0, scale=0))
    assert np.ptp(base) <= 30  # a 0.05-turn shift plus rounding on a pale colour: within a sixth of a turn
    same = hues(AugmentConfig(colour=0.25, shift_px=0, scale=0, hue=0.05))
    assert (base == same).all()  # hue=None is colour / 5: the same draws as before the option existed
    wide = hues(AugmentConfig(colour=0.25, shift_px=0, scale=0, hue=0.5))
    assert len(np.unique(wide // 30)) == 6  # every sixth of the hue circle


def test_raise_saturation_off_lowers_no_pixel_into_more_colour_and_keeps_the_draws():
    """With `raise_saturation=false` no pixel ends more saturated than the shifted picture had it, while hue,
    brightness and contrast still change (the same draws, the same random numbers taken), and a shift-only draw is
    untouched; on, a contrast gain saturates a dark grey-ish pixel."""
    from labrobfail_vlm.augment import Augment, AugmentConfig, hsv_saturation

    rng = np.random.default_rng(1)
    img = (rng.random((48, 48, 3)) * 255).astype(np.uint8)
    img[:24] = (40, 36, 36)  # a dark, nearly grey floor
    on, off = AugmentConfig(colour=0.75, hue=0.5), AugmentConfig(colour=0.75, hue=0.5, raise_saturation=False)
    raised = 0.0
    for k in range(30):
        a, b = Augment.draw(on, 1, np.random.default_rng(k)), Augment.draw(off, 1, np.random.default_rng(k))
        assert a.views == b.views and a.colour == b.colour and not b.raise_saturation
        plain = Augment(a.views, (1.0, 1.0, 1.0, 0.0)).image(img, 0)  # the shift and zoom alone
        x, y = a.image(img, 0), b.image(img, 0)
        assert (hsv_saturation(y) <= hsv_saturation(plain) + 1e-6).all()
        assert np.abs(y.astype(int) - plain.astype(int)).mean() > 1  # the colour still changed
        raised = max(raised, float((hsv_saturation(x) - hsv_saturation(plain)).max()))
    assert raised > 0.3
    still = Augment(((1.0, 3.0, -2.0),), (1.0, 1.0, 1.0, 0.0), raise_saturation=False)
    assert (still.image(img, 0) == Augment(still.views, still.colour).image(img, 0)).all()


def test_the_shipped_tower_matches_its_card_and_loads():
    import torch
    from safetensors.torch import load_file

    from labrobfail_vlm.model.tower import load_visual, read_card, shipped_dir, vision_overrides
    from labrobfail_vlm.train.tower import build_tower

    card = read_card(shipped_dir())  # the sha256 on the card is the shipped file's
    assert (shipped_dir() / "tower.safetensors").stat().st_size <= 25_000_000
    assert card["sha256"] in (shipped_dir() / "TOWER_CARD.md").read_text()
    tower = build_tower(vision_overrides(card), int(card["out_hidden_size"]), seed=1)
    load_visual(tower, shipped_dir())
    want = load_file(str(shipped_dir() / "tower.safetensors"))
    got = tower.state_dict()
    assert want.keys() == got.keys() and all(torch.equal(want[k], got[k]) for k in want)


def test_the_card_names_how_each_shard_folder_was_rendered(tmp_path):
    from labrobfail_vlm.train.tower_card import shard_origin

    def folder(name: str, **kw) -> str:
        (tmp_path / name).mkdir()
        (tmp_path / name / "run.json").write_text(json.dumps({"variant": "seen", "seed": 7, "backend_kwargs": kw}))
        return str(tmp_path / name)

    assert shard_origin(folder("plain", scene_family=None, button_lamp=False)).endswith("(seen, seed 7)")
    assert shard_origin(folder("both", scene_family="randomised", button_lamp=True, broken_glass=True)).endswith(
        "(seen, seed 7, scene family randomised, button lamp on, broken glass drawn)"
    )
    assert shard_origin(str(tmp_path / "absent")) == str(tmp_path / "absent")  # no run.json: the folder alone


def test_tower_data_reads_a_regenerated_shard_again(tower_shards, tmp_path):
    """A rebuild reuses the frame files of shards it has read (a killed build resumes) but not of a shard written
    again under the same name (another seed): its frames would be stale."""
    import os
    import shutil

    shards, out = tmp_path / "shards", tmp_path / "data"
    shutil.copytree(tower_shards, shards)
    frames = ["data.max_frames=4", "data.image_size=64", "data.ratios=[0.6,0.4]", "data.progress=false"]
    argv = [cli("build-tower-data"), f"data.shards={shards}", f"data.out_dir={out}", *frames]
    assert run_here(argv).returncode == 0
    before = json.loads((out / "index.json").read_text())["files"]
    first = sorted(shards.glob("shard-*.parquet"))[0]
    st = first.stat()
    os.utime(first, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))  # written again
    assert run_here(argv).returncode == 0
    after = json.loads((out / "index.json").read_text())["files"]
    changed = [a for a, b in zip(before, after) if a != b]
    assert len(before) == len(after) > 1 and len(changed) == 1 and f"-{first.stem}-" in changed[0]


def test_tower_data_refuses_two_runs_numbered_alike(tower_shards, tmp_path):
    """The same trajectory id in two shard folders (a folder given twice, or two generation runs numbered alike)
    would merge two pairs into one split group: refused in one line before anything is written."""
    import shutil

    twin = tmp_path / "twin"
    shutil.copytree(tower_shards, twin)
    out = tmp_path / "data"
    frames = ["data.max_frames=4", "data.image_size=64", "data.progress=false"]
    r = run_here([cli("build-tower-data"), f"data.shards=[{tower_shards},{twin}]", f"data.out_dir={out}", *frames])
    assert r.returncode == 2 and "is in both" in r.stderr and not out.exists()
