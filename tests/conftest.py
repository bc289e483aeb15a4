import socket
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest

ROOT = Path(__file__).resolve().parents[1]  # the tests run their subprocesses from the checkout root

# render_frames=null: every keyframe rendered, so the data tests can build grids of any size from the same run.
SMALL = [
    "scenarios=[press_button_red,open_oven_center,pick_place_bottle]",
    "image_size=48",
    "episodes_per_shard=2",
    "render_frames=null",
    "progress=false",
]


def gen(out, *extra, check=True):
    r = subprocess.run(
        [sys.executable, "scripts/generate.py", f"out_dir={out}", *SMALL, *extra],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    if check:
        assert r.returncode == 0, r.stderr
    return r


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
