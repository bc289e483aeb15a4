"""The library as a robot stack installs it: the wheel, installed into a fresh folder outside the checkout, holds
only project-named packages and diagnoses a real PyBullet episode with a tiny checkpoint from there."""

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from conftest import ROOT, run

pytestmark = pytest.mark.slow

PACKAGES = ("labrobfail_vlm", "sim_backends", "labrobfail_data")  # what the wheel holds, and all it holds

OUTSIDE = r"""
import io, json, sys
from pathlib import Path
import labrobfail_vlm, sim_backends
from labrobfail_vlm.analyzer import FailureAnalyzer
from labrobfail_vlm.config import CONFIG_DIR
from labrobfail_vlm.model.tiny import build_tiny
from PIL import Image
from sim_backends import make_backend

site = Path(sys.argv[1])
for mod in (labrobfail_vlm, sim_backends):
    assert Path(mod.__file__).resolve().is_relative_to(site), mod.__file__  # the installed copy, not the checkout
assert CONFIG_DIR.resolve().is_relative_to(site) and (CONFIG_DIR / "tasks" / "pybullet.yaml").is_file()
src = make_backend("pybullet", image_size=64)
src.reset(src.scenarios()[0], 3, "seen")
ep = src.execute(src.scripted_keyframes())
frames = [[Image.open(io.BytesIO(b)) for b in view if b] for view in ep.images]
model = build_tiny(Path(sys.argv[2]) / "tiny")
d = FailureAnalyzer.from_pretrained(model).analyze(frames, task=ep.task_meta.description)
print(json.dumps({"scenario": ep.scenario, "diagnosis": json.loads(d.to_json())}))
"""


def source_copy(dest: Path) -> Path:
    """What the wheel is built from: the checkout as a fresh clone has it (git's tracked and not-ignored files, so
    scripts/, tests/ and the root scripts are there for the package finder to leave out), copied outside it. A
    build in the checkout itself leaves build/ and labrobfail.egg-info/ there, and that stale metadata shadows the
    editable install's (a console script added later stays invisible to importlib.metadata until it is deleted)."""
    git = ["git", "ls-files", "-co", "--exclude-standard", "-z"]
    listed = subprocess.run(git, cwd=ROOT, capture_output=True) if shutil.which("git") else None
    if listed is None or listed.returncode != 0:  # not a git checkout: everything but what .gitignore names
        skip = shutil.ignore_patterns(".git", ".venv", "outputs", "build", "*.egg-info", "__pycache__", "wandb")
        return Path(shutil.copytree(ROOT, dest, symlinks=True, ignore=skip))
    for name in filter(None, listed.stdout.decode().split("\0")):
        (dest / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, dest / name, follow_symlinks=False)  # configs/ stays a link into the package
    return dest


def test_wheel_installs_outside_the_checkout_and_diagnoses_an_episode(tmp_path):
    pip = [sys.executable, "-m", "pip"]
    before = {p.name for p in ROOT.iterdir()}
    src = source_copy(tmp_path / "src")
    r = run([*pip, "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", str(tmp_path / "whl"), str(src)], cwd=None)
    assert r.returncode == 0, r.stderr[-2000:]
    wheel = next((tmp_path / "whl").glob("labrobfail-*.whl"))
    tops = {n.split("/")[0] for n in zipfile.ZipFile(wheel).namelist() if not n.split("/")[0].endswith(".dist-info")}
    assert tops == set(PACKAGES), tops  # nothing named data, scripts, ...
    made = {p.name for p in ROOT.iterdir()} - before  # the build wrote no metadata into the checkout
    assert not made & {"build", "labrobfail.egg-info"}, made
    site = tmp_path / "site"
    r = run([*pip, "install", "-q", "--no-deps", "--target", str(site), str(wheel)], cwd=None)
    assert r.returncode == 0, r.stderr[-2000:]
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site)}  # the installed copy first; the dependencies from this venv
    r = run([sys.executable, "-c", OUTSIDE, str(site), str(work)], cwd=work, env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert isinstance(out["diagnosis"]["failure"], bool) and 0 <= out["diagnosis"]["p_failure"] <= 1
    # the console scripts run from the installed copy too, with the shared command line
    r = run([str(site / "bin" / "labrobfail-infer"), "--help"], 300, cwd=work, env=env)
    assert r.returncode == 0 and "grid:" in r.stdout and "max_model_gb:" in r.stdout, r.stderr[-2000:]
