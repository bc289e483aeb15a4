"""Faults of long runs: training killed mid-run (and mid-save) resumes to the same final step and its model
evaluates; the diagnosis server killed under load comes back and every request is answered, with the clients'
request files untouched."""

import hashlib
import json
import os
import shutil
import signal
import threading
import time

import pytest
from conftest import ROOT, background, evaluate, free_port, run_here
from serve_fixtures import grids, mixed_model  # noqa: F401  (fixtures)
from test_serve import Server
from test_train import small_ds, tiny, tiny_train  # noqa: F401  (session fixtures)

pytestmark = pytest.mark.slow


def _wait_for(path, proc, timeout_s=300):
    t0 = time.monotonic()
    while not path.is_file():
        assert proc.poll() is None, "the run ended before it could be killed"
        assert time.monotonic() - t0 < timeout_s, f"{path} never appeared"
        time.sleep(0.05)


def test_an_augmented_run_resumed_ends_as_an_uninterrupted_one(tiny, small_ds, tmp_path):  # noqa: F811
    """Grid augmentation draws by epoch and pair: a run resumed from a checkpoint inside its second epoch (the
    loader skips the batches it trained) sees the grids an uninterrupted run sees and ends with its weights (to
    float rounding: 3e-7 here; a running generator's draws left them 4e-4 apart). The curriculum's phases are off:
    their switch is read as a batch is collated, a step or two ahead of it, so a checkpoint taken within two steps
    of a switch resumes with other flags (docs/EXPERIMENTS.md, 5 Dec)."""
    import torch
    from safetensors.torch import load_file

    def cmd(out, *extra):
        steps = ("save_steps=3", "save_total_limit=null", "max_steps=6", "epochs=4")
        off = ("grounding.pretrain_epochs=0", "curriculum.polarity_warmup=0", "curriculum.detect_first=0")
        return tiny_train(tiny, small_ds, out, "augment.enabled=true", *off, *steps, *extra)

    r = run_here(cmd(tmp_path / "full"))
    assert r.returncode == 0, r.stderr[-3000:]
    state = json.loads((tmp_path / "full" / "checkpoint-3" / "trainer_state.json").read_text())
    assert 1 < state["epoch"] < 2  # the resume begins inside an epoch that is not the first
    shutil.copytree(tmp_path / "full" / "checkpoint-3", tmp_path / "resumed" / "checkpoint-3")
    r = run_here(cmd(tmp_path / "resumed", "resume=true"))
    assert r.returncode == 0, r.stderr[-3000:]
    a, b = (load_file(str(tmp_path / d / "final" / "model.safetensors")) for d in ("full", "resumed"))
    assert a.keys() == b.keys() and all(torch.allclose(a[k], b[k], rtol=0, atol=1e-5) for k in a)


def test_training_killed_mid_run_resumes_to_the_final_step_and_evaluates(tiny, small_ds, tmp_path):  # noqa: F811
    out = tmp_path / "run"
    common = tiny_train(
        tiny,
        small_ds,
        out,
        *("grounding.pretrain_epochs=0", "save_steps=2", "save_total_limit=null", "logging_steps=1", "max_steps=8"),
    )
    proc = background(common)
    try:
        _wait_for(out / "checkpoint-2" / "trainer_state.json", proc)
        time.sleep(0.2)
        proc.send_signal(signal.SIGKILL)  # no chance to clean up
    finally:
        proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL and not (out / "final").exists()
    done = sorted(int(d.name.split("-")[1]) for d in out.glob("checkpoint-*"))
    # what a kill while saving leaves: a newer checkpoint folder whose trainer_state.json (written last) is cut short
    partial = out / f"checkpoint-{done[-1] + 2}"
    shutil.copytree(out / f"checkpoint-{done[-1]}", partial)
    (partial / "trainer_state.json").write_text('{"global_step": ')
    r = run_here([*common, "resume=true"])  # the killed run was a process; its resume runs here
    assert r.returncode == 0, r.stderr[-3000:]
    assert f"skipping {partial}" in r.stderr
    assert json.loads((out / "train_summary.json").read_text())["global_step"] == 8
    steps = [row["step"] for row in json.loads((out / "progress.json").read_text())]
    assert steps == sorted(set(steps)) and steps[-1] == 8  # the learning curve has no duplicated or lost rows
    no_baselines = ("split=test", "baselines=[]", "q6_template=false", f"out_dir={tmp_path / 'eval'}", "progress=false")
    r = evaluate(f"model={out / 'final'}", small_ds, *no_baselines, call=run_here)
    assert r.returncode == 0, r.stderr[-3000:]
    results = json.loads((tmp_path / "eval" / "results.json").read_text())
    assert results["detection"]["trajectories"] > 0
    # the learning curve reads the resumed run: one point per checkpoint in progress.json (the cut-short one is not),
    # and its last point (checkpoint-8, the final weights) scores as the bench of final
    curve = tmp_path / "curve.png"
    curve_args = [f"run_dir={out}", f"dataset_dir={small_ds}", "split=test", f"out={curve}"]
    r = run_here(["scripts/learning_curve.py", *curve_args])
    assert r.returncode == 0, r.stderr[-3000:]
    points = json.loads(curve.with_suffix(".json").read_text())["points"]
    assert [p["step"] for p in points] == steps and curve.is_file()
    assert points[-1]["q2"] == results["q2"]
    # nothing to resume from is one line
    r = run_here([*common[:-3], f"output_dir={tmp_path / 'empty'}", "resume=true", "progress=false"])
    assert r.returncode == 2 and "no complete checkpoint" in r.stderr.strip().splitlines()[-1], r.stderr
    # a complete-looking checkpoint whose weights or optimizer state cannot be read (a full disk while saving): one
    # line naming the file, not the trainer's traceback half-way through loading it
    for name in (sorted(p.name for p in (out / "checkpoint-8").glob("*.safetensors"))[0], "optimizer.pt"):
        bad = tmp_path / f"bad_{name}"
        shutil.copytree(out / "checkpoint-8", bad / "checkpoint-8")
        (bad / "checkpoint-8" / name).write_bytes(b"")
        r = run_here([*common[:-3], f"output_dir={bad}", "resume=true", "progress=false"])
        last = r.stderr.strip().splitlines()[-1]
        assert r.returncode == 2 and last.startswith("error: resume:") and name in last and "Traceback" not in r.stderr
    # a DeepSpeed state that names code to run (DeepSpeed unpickles its states in full): refused before it loads
    import torch

    bad = tmp_path / "bad_deepspeed"
    shutil.copytree(out / "checkpoint-8", bad / "checkpoint-8")
    (bad / "checkpoint-8" / "global_step8").mkdir()
    torch.save({"module": _Planted(bad / "ran")}, bad / "checkpoint-8" / "global_step8" / "mp_rank_00_model_states.pt")
    r = run_here([*common[:-3], f"output_dir={bad}", "resume=true", "progress=false"])
    last = r.stderr.strip().splitlines()[-1]
    assert r.returncode == 2 and "beyond DeepSpeed's plain state (io.open)" in last
    assert not (bad / "ran").exists()
    # each checkpoint records the settings that decide its weights (not where or how often it saves); a resume under
    # another of them (a learning rate) is one line naming it, and the checkpoint is left as it was
    recorded = json.loads((out / "checkpoint-8" / "train_settings.json").read_text())
    assert "output_dir" not in recorded and "resume" not in recorded and recorded["lr"]["text"] != 4.321e-4
    other = tmp_path / "other"
    shutil.copytree(out / "checkpoint-8", other / "checkpoint-8")
    before = {f.name: _sha(f) for f in (other / "checkpoint-8").iterdir() if f.is_file()}
    r = run_here([*common[:-3], f"output_dir={other}", "resume=true", "progress=false", "lr.text=4.321e-4"])
    last = r.stderr.strip().splitlines()[-1]
    assert r.returncode == 2 and last.startswith("error: lr.text:") and "this run has 0.0004321;" in last, r.stderr
    assert {f.name: _sha(f) for f in (other / "checkpoint-8").iterdir() if f.is_file()} == before
    assert not (other / "final").exists() and "Traceback" not in r.stderr


class _Planted:
    """A pickle that creates a file when it is loaded in full."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.parametrize("n", [8])
def test_server_killed_under_load_restarts_and_every_request_is_answered(mixed_model, grids, tmp_path, n):  # noqa: F811
    from labrobfail_vlm.serve.client import DiagnosisClient

    files = []
    for i in range(n):
        f = tmp_path / f"req{i}.png"
        grids[i % len(grids)].save(f)
        files.append(f)
    before = {f: _sha(f) for f in files}
    port = free_port()
    args = ["--port", str(port), "--max-batch", "2", "--max-wait-ms", "50"]
    first = Server(mixed_model, tmp_path / "first.log", *args, token=None)
    url = first.url
    got: list = [None] * n
    errors: list = []

    def ask(i):
        try:
            got[i] = DiagnosisClient(url, retries=300, retry_wait_s=0.2).diagnose(grid=files[i], task=f"task {i}")
        except Exception as e:  # noqa: BLE001 - reported by the assert below
            errors.append(f"{i}: {type(e).__name__}: {e}")

    threads = [threading.Thread(target=ask, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    time.sleep(0.3)
    first.proc.send_signal(signal.SIGKILL)  # under load: requests queued, decoding, replying
    first.proc.wait(timeout=30)
    second = Server(mixed_model, tmp_path / "second.log", *args, token=None)
    try:
        for t in threads:
            t.join(timeout=300)
        assert not errors and all(g is not None for g in got), errors
        assert DiagnosisClient(url).health()["batches"] >= 1  # the kill did cut requests off: the restart answered
    finally:
        assert second.stop() == 0
    from labrobfail_vlm.analyzer import FailureAnalyzer

    fa = FailureAnalyzer.from_pretrained(mixed_model)
    for i, g in enumerate(got):
        want = json.loads(fa.analyze(grids[i % len(grids)], f"task {i}").to_json())
        assert g.pop("p_failure") == pytest.approx(want.pop("p_failure"), abs=1e-4)
        assert g == want
    assert {f: _sha(f) for f in files} == before  # the request files are the clients' and stay as they were
    assert not [p for p in os.listdir(ROOT) if p.endswith(".tmp")]  # and the server left nothing half-written


def test_an_atomic_write_that_fails_leaves_the_old_file_and_no_temp_file(tmp_path, monkeypatch):
    """Every atomic write goes through labrobfail_vlm.io: a write cut short (here data that is not bytes) keeps the
    previous file whole and takes its temp file with it; each call writes under a temp name of its own, so two
    processes that write the same file together never share one."""
    from labrobfail_vlm import io

    out = tmp_path / "r.json"
    io.atomic_write_bytes(out, b"old")
    with pytest.raises(TypeError):
        io.atomic_write_bytes(out, "not bytes")  # type: ignore[arg-type]
    assert out.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == ["r.json"]
    opened: list[str] = []

    def spy(file, *a, **kw):
        opened.append(str(file))
        return open(file, *a, **kw)

    monkeypatch.setattr(io, "open", spy, raising=False)  # the module's name for the builtin
    io.atomic_write_bytes(out, b"a")
    io.atomic_write_bytes(out, b"b")
    assert len(set(opened)) == 2 and all(p.endswith(".tmp") for p in opened) and out.read_bytes() == b"b"


def test_a_folder_swapped_in_is_whole_and_a_kill_between_renames_is_read_back(tmp_path, monkeypatch):
    """swap_in puts a fully written folder in place of the old one (train's final/, the tower's resume point);
    between its two renames only <name>.old exists, which `swapped` reads back. A resume point saved into a folder
    an earlier run left complete is not complete until its marker is written again."""
    import torch

    from labrobfail_vlm import io

    final, tmp = tmp_path / "final", tmp_path / "final.tmp"
    for n, text in enumerate(("old", "new")):
        tmp.mkdir()
        (tmp / "w").write_text(text)
        (tmp / "m.json").write_text("{}")
        io.swap_in(tmp, final)
        assert (final / "w").read_text() == text and sorted(p.name for p in tmp_path.iterdir()) == ["final"]
    final.rename(tmp_path / "final.old")  # a kill after the first rename
    assert io.swapped(final, "m.json") == tmp_path / "final.old"
    assert io.swapped(tmp_path / "other", "m.json") == tmp_path / "other"
    # the next save from there: the .old (the only whole copy) stays until the new folder is in place
    tmp.mkdir()
    (tmp / "m.json").write_text("{}")

    def killed(self, target):
        raise KeyboardInterrupt  # a kill at the rename

    with monkeypatch.context() as m:
        m.setattr(type(tmp), "rename", killed)
        with pytest.raises(KeyboardInterrupt):
            io.swap_in(tmp, final)
    assert (tmp_path / "final.old" / "w").read_text() == "new"
    # save_resume_state: a stale marker goes before the tensors are written
    step = tmp_path / "step-2"
    step.mkdir()
    (step / "state.json").write_text('{"step": 2}')
    with pytest.raises(TypeError):
        io.save_resume_state(step, {"x": torch.zeros(1)}, {"step": object()}, "state.json")  # the marker fails
    assert io.newest_complete(tmp_path, "step", "state.json") is None
