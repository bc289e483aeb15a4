"""Compare LabRobFail-Sim throughput across simulator backends: one table from scripts/bench_sim.py's JSON.

Run as:
    python scripts/bench_backends.py [backends=[pybullet,maniskill]] [episodes=28] [image_size=192]
                                     [out=outputs/bench_backends.json]
    python scripts/bench_backends.py --backends pybullet --episodes 8

Each backend runs `scripts/bench_sim.py backend=NAME` in a child process of its own (so peak memory is its
own), on its own scenario mix (the generator's pair plan for seed 0). Writes `out` (backend -> bench_sim's
JSON) and the same as a Markdown table next to it (`.md`). The "2 views" row is the backend's default
rendering variant.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from labrobfail_vlm.config import ConfigError, cli_main, load_config, require_ints
from labrobfail_vlm.io import atomic_write_bytes, atomic_write_json

SCRIPTS = Path(__file__).resolve().parent  # bench_sim.py runs from here, with the repository root as its cwd

DEFAULTS = """
backends: [pybullet, maniskill]    # simulator backends to compare (a list, or one name / comma-separated names)
episodes: 28                       # episodes per bench_sim row, per backend
image_size: 192                    # square rendered views, px
out: outputs/bench_backends.json   # the JSON result (the Markdown table goes next to it, .md)
"""

ROWS = [  # (key, label) of the table, in order; "rendered" = the first rendered_2x* key bench_sim wrote
    ("physics_only_episodes_per_hour_per_core", "physics only, episodes/h/core"),
    ("rendered", "2 views, default renderer, episodes/h/core"),
    ("end_to_end_episodes_per_hour_per_core", "end to end to shards, 1 worker, episodes/h"),
    ("end_to_end_2_workers_episodes_per_hour", "end to end to shards, 2 workers, episodes/h"),
    ("speedup_2_workers", "speed-up with 2 workers"),
    ("peak_rss_mb_main_process", "peak RSS, in-process runs (MB)"),
    ("peak_rss_mb_worker", "peak RSS, a worker (MB)"),
    ("scenarios", "scenarios in the mix"),
]


def cell(res: dict, key: str) -> str:
    if key == "rendered":
        key = next((k for k in res if k.startswith("rendered_2x")), key)
    return str(res.get(key, ""))


def table(results: dict[str, dict]) -> str:
    names = list(results)
    lines = ["| | " + " | ".join(names) + " |", "| --- |" + " --- |" * len(names)]
    for key, label in ROWS:
        lines.append(f"| {label} | " + " | ".join(cell(results[b], key) for b in names) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> int:
    cfg = load_config(DEFAULTS, argv)
    backends = cfg.backends.split(",") if isinstance(cfg.backends, str) else cfg.backends
    if not isinstance(backends, Sequence) or not backends or not all(isinstance(b, str) and b for b in backends):
        raise ConfigError(f"backends: expected a list of backend names, got {cfg.backends!r}")
    require_ints(cfg, ("episodes",), 2)
    require_ints(cfg, ("image_size",))
    n, size = cfg.episodes, cfg.image_size
    out = Path(str(cfg.out))
    results = {}
    with tempfile.TemporaryDirectory() as d:
        for backend in list(backends):
            one = Path(d) / f"{backend}.json"
            r = subprocess.run(
                [
                    sys.executable,
                    str(SCRIPTS / "bench_sim.py"),
                    f"backend={backend}",
                    f"episodes={n}",
                    f"image_size={size}",
                    f"out={one}",
                ],
                cwd=SCRIPTS.parent,
                capture_output=True,
                text=True,
            )
            if r.returncode != 0:
                tail = (r.stderr.strip().splitlines() or ["no output"])[-1]
                print(f"error: {backend}: {tail}", file=sys.stderr)
                return 2
            results[backend] = json.loads(one.read_text())
    atomic_write_json(out, results, indent=2)
    atomic_write_bytes(out.with_suffix(".md"), table(results).encode())
    print(table(results))
    return 0


if __name__ == "__main__":
    cli_main(main, __doc__)
