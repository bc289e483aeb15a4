import os
import socket
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest

ROOT = Path(__file__).resolve().parents[1]  # the tests run their subprocesses from the checkout root
BIN = Path(sys.executable).parent  # the venv's console scripts (labrobfail-*), as a user runs them


def cli(name: str) -> str:
    """The console script labrobfail-<name> of this venv."""
    return str(BIN / f"labrobfail-{name}")


def program(script: str) -> list[str]:
    """A console script (labrobfail-*) of this venv, or a checkout file (train.py, infer.py) run by this Python."""
    return [str(BIN / script)] if script.startswith("labrobfail-") else [sys.executable, script]


def run(argv: list, timeout: float = 600, **kw) -> subprocess.CompletedProcess:
    """Run a command to its end from the checkout root (unless cwd= says otherwise), its output captured as text."""
    kw.setdefault("cwd", ROOT)
    return subprocess.run(argv, capture_output=True, text=True, timeout=timeout, **kw)


# the checkout's thin root scripts and the console script each one calls
ROOT_SCRIPTS = {"train.py": "labrobfail-train", "infer.py": "labrobfail-infer"}


def run_here(argv: list, env: dict | None = None) -> subprocess.CompletedProcess:
    """What run(argv) returns, the console script's entry point called in this process instead: the same code from
    sys.argv to the exit code, without a Python start and the imports (torch, transformers, peft: about 8 s of a
    12 s tiny training run on 2 cores). For a test's one-line-error cases and for the runs whose process is not
    what the test is about; a run a test kills, signals or serves from stays a process, and every console script
    still runs as one somewhere in the suite (an uncaught exception here fails the test: stricter).
    `env`: variables set for the call (and restored after it), as is torch's thread count (a run may set it)."""
    import contextlib
    import functools
    import io
    from importlib.metadata import entry_points

    import torch

    argv = [str(a) for a in argv]
    if argv[0] == sys.executable:  # [python, train.py, ...]
        argv = argv[1:]
    argv[0] = ROOT_SCRIPTS.get(argv[0], argv[0])
    name = Path(argv[0]).name
    if name.endswith(".py"):  # a checkout script (scripts/train_act.py): run as `python scripts/x.py` runs it
        import runpy

        entry = functools.partial(runpy.run_path, str(ROOT / argv[0]), run_name="__main__")
    else:
        (ep,) = entry_points(group="console_scripts", name=name)
        entry = ep.load()
    out, err, code = io.StringIO(), io.StringIO(), 0
    old, saved = sys.argv, dict(os.environ)
    threads = torch.get_num_threads()
    sys.argv = [name, *argv[1:]]
    os.environ.update(env or {})
    try:
        with contextlib.chdir(ROOT), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            entry()
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    finally:
        sys.argv = old
        os.environ.clear()
        os.environ.update(saved)
        torch.set_num_threads(threads)
    return subprocess.CompletedProcess(argv, code, out.getvalue(), err.getvalue())


def background(argv: list) -> subprocess.Popen:
    """Start a command from the checkout root, its output thrown away (a run a test kills part-way)."""
    return subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def evaluate(source: str, dataset, *extra: str, timeout: float = 600, call=None) -> subprocess.CompletedProcess:
    """labrobfail-evaluate of `source` (model=... or predictions=...) on the dataset folder `dataset`, as a process
    (or through `call`, e.g. run_here)."""
    argv = [cli("evaluate"), source, f"dataset_dir={dataset}", *extra]
    return call(argv) if call else run(argv, timeout)


def supervise_front(
    out, policy: list[str], task: str, trials: int, image_size: int, *extra: str, timeout: float = 600, here=False
):
    """labrobfail-supervise: `trials` trials of `task` driven by `policy` (its settings), on the front camera at
    `image_size` px, written to `out`; `extra` settings go after the camera. A process, or this one with `here`."""
    argv = [
        cli("supervise"),
        *policy,
        f"task={task}",
        f"trials={trials}",
        f"image_size={image_size}",
        "cameras=[front]",
    ]
    argv = [*argv, *extra, "progress=false", f"out_dir={out}"]
    return run_here(argv) if here else run(argv, timeout)


def serve_policy(*args: str, **kw) -> subprocess.Popen:
    """labrobfail-serve-policy started from the checkout root, its stdout and stderr piped as text."""
    return subprocess.Popen(
        [cli("serve-policy"), *args], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw
    )


def scripted_server(*extra: str):
    """For a fixture: labrobfail-serve-policy serving the scripted policy on a free loopback port; yields its URL
    and process once, then stops it."""
    p = serve_policy("policy=scripted", "port=0", *extra)
    line = p.stdout.readline()
    assert line.startswith("serving scripted on http://127.0.0.1:"), line + p.stderr.read()
    yield line.split()[-1], p
    p.terminate()
    p.wait(timeout=10)


# render_frames=null: every keyframe rendered, so the data tests can build grids of any size from the same run.
SMALL_IMAGES = ["image_size=48", "episodes_per_shard=2", "render_frames=null", "progress=false"]
SMALL = ["scenarios=[press_button_red,open_oven_center,pick_place_bottle]", *SMALL_IMAGES]


def gen(out, *extra, check=True, here=False):
    """labrobfail-generate into `out` at the tests' small sizes, as a process (or in this one: run_here)."""
    argv = [cli("generate"), f"out_dir={out}", *SMALL, *extra]
    r = run_here(argv) if here else run(argv)
    if check:
        assert r.returncode == 0, r.stderr
    return r


def begin_episode(src, scenario: str = "pick_place_beaker_small", seed: int = 0) -> list:
    """reset + begin an episode of `scenario` on a backend; the scripted plan, for the test to step."""
    src.reset(scenario, seed, "seen")
    plan = src.scripted_keyframes()
    src.begin()
    return plan


def free_port() -> int:
    """A loopback port nobody holds now (a fixed one collides with a lingering or concurrent run)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def rows(out):
    return sorted(
        (r for p in sorted(Path(out).glob("shard-*.parquet")) for r in pq.read_table(p).to_pylist()),
        key=lambda r: r["episode_id"],
    )


@pytest.fixture(scope="session")
def run6(tmp_path_factory):
    """A real 3-pair PyBullet run (6 episodes, 48 px images), shared by the data tests; seed 5: all three injected
    episodes fail (three types), so every split of the small dataset has a failure."""
    out = tmp_path_factory.mktemp("gen") / "a"
    gen(out, "num_episodes=6", "seed=5")
    return out


def injected_rows(src, scenario: str, specs: list[dict], seed: int = 1) -> list[dict]:
    """Manifest rows of real injected episodes, one per perturbation spec (drawn as the generator draws them)."""
    import numpy as np

    from sim_backends.failure_generator import apply_spec
    from sim_backends.shards import episode_row

    out = []
    for k, spec in enumerate(specs):
        src.reset(scenario, seed + k, "seen")
        kfs, events, prov = apply_spec(spec, src.scripted_keyframes(), src.object_positions(), np.random.default_rng(k))
        ep = src.execute(kfs, events)
        ep.perturbation, ep.episode_id, ep.pair_id, ep.role = prov, f"ep{k}", f"pair{k}", "injected"
        out.append(episode_row(ep))
    return out


# the paper's draws, forced so that one short run shows each direction: a several-parameter physics draw (mixed
# signs), a closed command that opens (the carry) and an open command that stays shut (the release)
SIGNS_AND_FAULTS = [
    {
        "level": "physics",
        "at": ["s1_carry"],
        "params": [
            {"param": p, "target": t, "alpha": 0.9}
            for p, t in (("grip_force", "robot"), ("friction", "obj"), ("mass", "obj"))
        ],
    },
    {
        "level": "physics",
        "at": ["s1_carry"],
        "params": [
            {"param": p, "target": t, "alpha": 0.9}
            for p, t in (("grip_force", "robot"), ("friction", "obj"), ("mass", "obj"))
        ],
    },
    {"level": "control", "op": "corrupt_gripper", "keyframes": ["s1_carry"], "lambda": 1.0},
    {"level": "control", "op": "corrupt_gripper", "keyframes": ["s1_release"], "lambda": 1.0},
]


def check_injection_summary(rows: list[dict]) -> None:
    from sim_backends.shards import injection_summary

    inj = injection_summary(rows)
    signs = {s for v in inj["physics_events"].values() for s in v}
    assert set(inj["physics_events"]) == {"grip_force", "friction", "mass"} and signs == {"+", "-"}, inj
    assert inj["gripper_faults"] == {"to_closed": 1, "to_open": 1}, inj
    assert sum(sum(v.values()) for v in inj["by_operator"].values()) == len(rows)
    fails = {r["failure_type"] for r in rows[2:]}
    assert fails == {"gripper_control_failure"}, [r["evidence"] for r in rows[2:]]  # both faults explained as such


# Test files whose tests train a model, run supervised trials or episodes by the dozen, or start servers: `slow`
# (make test runs them; make test-fast, `-m "not slow"`, leaves them out), as are the browser and ManiSkill tests.
SLOW_FILES = {
    "test_act.py",
    "test_checkpoint_guard.py",
    "test_drawing.py",
    "test_endpoint.py",
    "test_executable.py",
    "test_faults.py",
    "test_grounding.py",
    "test_infer_bench.py",
    "test_openvla.py",
    "test_policy_faults.py",
    "test_serve.py",
    "test_server_bounds.py",
    "test_supervise.py",
    "test_tower.py",
    "test_tower_cache.py",
    "test_train.py",
    "test_video.py",
    "test_batching.py",
    "test_wheel.py",
}


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.path.name in SLOW_FILES or {"browser", "maniskill"} & {m.name for m in item.iter_markers()}:
            item.add_marker(pytest.mark.slow)
