import socket
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

# render_frames=null: every keyframe rendered, so the data tests can build grids of any size from the same run.
SMALL = ["scenarios=[press_button_red,open_oven_center,pick_place_bottle]", "image_size=48", "episodes_per_shard=2",
         "render_frames=null", "progress=false"]


def gen(out, *extra, check=True):
    r = subprocess.run([sys.executable, "scripts/generate.py", f"out_dir={out}", *SMALL, *extra], cwd=ROOT,
                       capture_output=True, text=True, timeout=600)
    if check:
        assert r.returncode == 0, r.stderr
    return r


def free_port() -> int:
    """A loopback port nobody holds now (a fixed one collides with a lingering or concurrent run)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def rows(out):
    return sorted((r for p in sorted(Path(out).glob("shard-*.parquet")) for r in pq.read_table(p).to_pylist()),
                  key=lambda r: r["episode_id"])


@pytest.fixture(scope="session")
def run6(tmp_path_factory):
    """A real 3-pair PyBullet run (6 episodes, 48 px images), shared by the data tests."""
    out = tmp_path_factory.mktemp("gen") / "a"
    gen(out, "num_episodes=6", "seed=3")
    return out
