"""Frame grounding (labrobfail_vlm/train/grounding.py): targets, the token-to-cell map, the head, a real run."""

import json
from pathlib import Path

import pytest
import torch
from conftest import background, run_here
from test_train import scratch_train, small_ds, tiny, tiny_train  # noqa: F401  (session fixtures)


def test_frame_targets_follow_the_failure_frame_and_the_shown_cells():
    from labrobfail_vlm.train.grounding import frame_targets

    assert frame_targets({"success": True, "frame": None, "frames": 6}, 8) == [0, 0, 0, 0, 0, 0, -1, -1]
    assert frame_targets({"success": False, "frame": 3, "frames": 6}, 8) == [0, 0, 1, 1, 1, 1, -1, -1]
    # a prefix grid shows its first `visible` frames only
    assert frame_targets({"success": False, "frame": 2, "frames": 8, "visible": 3}, 8) == [0, 1, 1] + [-1] * 5


def test_cell_index_maps_tokens_to_time_steps_and_views():
    from labrobfail_vlm.grid import GridConfig
    from labrobfail_vlm.train.grounding import cell_index

    g = GridConfig(width=512, height=512, max_frames=8, columns=4)  # 4 rows (2 bands x 2 views) of 128 px cells
    idx = cell_index(g, 2, 16, 16).view(16, 16)
    assert idx[0, 0] == 0 and idx[3, 3] == 0  # t=0, view 0: the top-left 4x4 tokens
    assert idx[4, 0] == 1  # t=0, view 1
    assert idx[0, 15] == 3 * 2  # t=3, view 0
    assert idx[8, 4] == 5 * 2 and idx[15, 15] == 7 * 2 + 1  # the second band: t=5 view 0, t=7 view 1
    assert torch.bincount(idx.flatten()).tolist() == [16] * 16
    # the default 1536x768 grid of 16 frames: 6x6 tokens per cell, every token in a cell
    d = GridConfig()
    idx = cell_index(d, 2, 24, 48)
    assert (idx >= 0).all() and torch.bincount(idx).tolist() == [36] * 32


@pytest.mark.parametrize("kind", ["token", "cell"])
def test_head_reads_each_time_step_from_its_own_cells(kind):
    from labrobfail_vlm.grid import GridConfig
    from labrobfail_vlm.train.grounding import grounding_loss, make_head

    torch.manual_seed(0)
    g = GridConfig(width=512, height=512, max_frames=8, columns=4)
    head = make_head(kind, 8, g, 2)
    tokens = torch.zeros(256, 8)
    base = head(tokens, 16, 16)
    tokens.view(16, 16, 8)[8:12, 4:8] = 3.0  # the cell of t=5 in view 0
    moved = head(tokens, 16, 16)
    assert torch.allclose(moved[[0, 1, 2, 3, 4, 6, 7]], base[[0, 1, 2, 3, 4, 6, 7]])
    assert not torch.isclose(moved[5], base[5])
    # the loss trains: a few steps separate a grid whose late cells differ from its unchanged twin
    fail, ok = torch.randn(256, 8), None
    ok = fail.clone()
    fail.view(16, 16, 8)[8:16, :] += 1.0  # frames 5-8 change
    tok = torch.cat([fail, ok])
    thw = torch.tensor([[1, 32, 32], [1, 32, 32]])
    y = torch.tensor([[0, 0, 0, 0, 1, 1, 1, 1], [0.0] * 8])
    opt = torch.optim.Adam(head.parameters(), lr=0.05)
    first = None
    for _ in range(40):
        loss = grounding_loss(head, tok, thw, y, torch.tensor([0, 0]))
        first = float(loss) if first is None else first
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(loss) < 0.5 * first
    z = torch.stack([head(fail, 16, 16), head(ok, 16, 16)])
    assert (z[0, 4:] > z[1, 4:]).all()


def test_training_with_grounding_logs_saves_and_resumes(tiny, small_ds, tmp_path):  # noqa: F811
    out = tmp_path / "g"
    common = tiny_train(tiny, small_ds, out, "grounding.weight=1.0", "save_steps=2", "logging_steps=1")
    common.append("grounding.pretrain_epochs=1")  # the resume's too: a checkpoint resumes under its own settings
    r = run_here([*common, "max_steps=2"])
    assert r.returncode == 0, r.stderr[-3000:]
    assert "grounding_loss" in r.stdout + r.stderr
    # stage A ran before the VQA steps, and the learning curve's clocks count it
    pre = json.loads((out / "train_summary.json").read_text())["grounding_pretrain"]
    assert pre["epochs"] == 1 and pre["first_epoch_loss"] > 0
    assert json.loads((out / "progress.json").read_text())[0]["cpu_s"] >= pre["cpu_s"]
    from safetensors.torch import load_file

    saved = load_file(str(out / "checkpoint-2" / "grounding_head.safetensors"))
    assert saved and all(torch.isfinite(t).all() for t in saved.values())
    r = run_here([*common, "max_steps=3", "resume=true"])
    assert r.returncode == 0, r.stderr[-3000:]
    summary = json.loads((out / "train_summary.json").read_text())
    assert summary["global_step"] == 3 and "grounding_pretrain" not in summary  # the checkpoint holds stage A
    # an old dataset without view counts is refused in one line
    traj = json.loads((small_ds / "trajectories.json").read_text())
    old = tmp_path / "old"
    old.mkdir()
    for f in small_ds.iterdir():
        if f.is_file() and f.name != "trajectories.json":
            (old / f.name).symlink_to(f)
    (old / "images").symlink_to(small_ds / "images")
    (old / "trajectories.json").write_text(json.dumps([{k: v for k, v in t.items() if k != "views"} for t in traj]))
    on_old = [f"dataset_dir={old}", f"output_dir={tmp_path}/o", "max_steps=1", "grounding.weight=1"]
    r = run_here([*common[:4], *on_old, "wandb.enabled=false"])
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "grounding" in r.stderr.strip().splitlines()[-1]


def test_a_run_from_a_checkpoint_repeats_exactly(tiny, small_ds, tmp_path):  # noqa: F811
    """The same seed gives the same run when it starts from a checkpoint (a third stage): the grounding head is
    initialised after train.py seeds, not from torch's start-up seed."""
    got = []
    for name in ("a", "b"):
        argv = scratch_train(tiny, small_ds, tmp_path / name)
        steps = ["global_batch=2", "per_device_batch=2", "max_steps=2", "grounding.weight=1.0"]
        r = run_here([*argv, *steps, "grounding.pretrain_epochs=0", "wandb.enabled=false", "progress=false"])
        assert r.returncode == 0, r.stderr[-3000:]
        s = json.loads((tmp_path / name / "train_summary.json").read_text())
        got.append((s["first_loss"], s["last_loss"]))
    assert got[0] == got[1]


@pytest.mark.parametrize(
    "bad, field",
    [
        ("grounding.weight=-1", "grounding.weight"),
        ("grounding.rank=-0.5", "grounding.rank"),
        ("grounding.head=mlp", "grounding.head"),
        ("grounding.pretrain_epochs=-2", "grounding.pretrain_epochs"),
        ("grounding.weight=0", "grounding.pretrain_epochs"),  # the tiny preset's stage A needs the head
        ("deepspeed=configs/ds_zero3.json", "grounding.weight"),
    ],
)
def test_bad_grounding_config_is_one_line(tiny, small_ds, tmp_path, bad, field):  # noqa: F811
    # in this process (the train CLI's one-line errors run as a process in test_train)
    r = run_here([*scratch_train(tiny, small_ds, f"{tmp_path}/o"), bad, "wandb.enabled=false"])
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith(f"error: {field}:")


def test_resuming_a_run_made_without_grounding_is_one_line(tiny, small_ds, tmp_path):  # noqa: F811
    """On a scratch tower the tiny preset grounds by default; a run without the head cannot resume with one."""
    common = [*scratch_train(tiny, small_ds, f"{tmp_path}/o"), "save_steps=1", "wandb.enabled=false", "progress=false"]
    r = run_here([*common, "max_steps=1", "grounding.weight=0", "grounding.pretrain_epochs=0"])
    assert r.returncode == 0, r.stderr[-2000:]
    r = run_here([*common, "max_steps=2", "resume=true"])
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("error: grounding.pretrain_epochs:")  # its recorded settings
    for f in Path(f"{tmp_path}/o").glob("checkpoint-*/train_settings.json"):  # a checkpoint from before they were
        f.unlink()
    r = run_here([*common, "max_steps=2", "resume=true"])
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("error: resume:") and "grounding.weight=0" in r.stderr


def test_a_run_killed_in_stage_a_resumes_and_ends_as_an_uninterrupted_one(tiny, small_ds, tmp_path):  # noqa: F811
    import shutil
    import time

    from safetensors.torch import load_file

    from labrobfail_vlm.train.grounding import stage_a_state

    def cmd(out, *extra):
        return tiny_train(
            tiny,
            small_ds,
            out,
            "max_steps=1",
            "grounding.weight=1.0",
            "grounding.pretrain_epochs=6",
            "augment.enabled=true",  # its generator is part of what a resume restores
            *extra,
        )

    r = run_here(cmd(tmp_path / "full"))  # the uninterrupted run: in this process (the killed one is not)
    assert r.returncode == 0, r.stderr[-3000:]
    full = json.loads((tmp_path / "full" / "train_summary.json").read_text())
    assert "resumed_at_epoch" not in full["grounding_pretrain"]
    # older epochs removed; beside the newest, the settings a resume of stage A is checked against
    assert sorted(d.name for d in (tmp_path / "full" / "stage_a").iterdir()) == ["epoch-6", "train_settings.json"]
    # the same run, killed once stage A has saved an epoch
    out = tmp_path / "killed"
    p = background(cmd(out))
    try:
        while stage_a_state(out) is None and p.poll() is None:
            time.sleep(0.05)
    finally:
        p.kill()
        p.wait()
    at = stage_a_state(out)
    assert at is not None and not (out / "train_summary.json").exists()
    done = int(at.name.split("-")[1])
    assert 1 <= done < 6
    r = run_here(cmd(out, "resume=true", "grounding.lr=0.0123"))  # another stage A: refused before anything loads
    assert r.returncode == 2 and r.stderr.strip().splitlines()[-1].startswith("error: grounding.lr:"), r.stderr[-2000:]
    assert stage_a_state(out) == at
    r = run_here(cmd(out, "resume=true"))
    assert r.returncode == 0, r.stderr[-3000:]
    again = json.loads((out / "train_summary.json").read_text())
    assert again["grounding_pretrain"]["resumed_at_epoch"] >= done
    for k in ("first_epoch_loss", "last_epoch_loss"):
        assert again["grounding_pretrain"][k] == full["grounding_pretrain"][k]
    assert again["first_loss"] == full["first_loss"]
    a, b = (load_file(str(d / "final" / "model.safetensors")) for d in (tmp_path / "full", out))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    # a stage A of another length is not resumed silently
    other = tmp_path / "other"
    shutil.copytree(tmp_path / "full" / "stage_a", other / "stage_a")
    r = run_here([*cmd(other, "resume=true"), "grounding.pretrain_epochs=3"])  # a refusal: in the test's process
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("error: grounding.pretrain_epochs:")  # its recorded settings
    (other / "stage_a" / "train_settings.json").unlink()  # a stage A saved before they were recorded
    r = run_here([*cmd(other, "resume=true"), "grounding.pretrain_epochs=3"])
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("error: resume:") and "6 epochs" in r.stderr
