"""Compare LabRobFail-Sim throughput across simulator backends: one table from scripts/bench_sim.py's JSON.

Run as:
    python scripts/bench_backends.py [backends=[pybullet,maniskill]] [episodes=28] [image_size=192] [out=outputs/bench_backends.json]

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
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from omegaconf import OmegaConf  # noqa: E402

from labrobfail_vlm.io import atomic_write_bytes, atomic_write_json  # noqa: E402

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
    args = OmegaConf.from_dotlist(argv)
    n, size = int(args.get("episodes", 28)), int(args.get("image_size", 192))
    out = Path(args.get("out", "outputs/bench_backends.json"))
    results = {}
    with tempfile.TemporaryDirectory() as d:
        for backend in list(args.get("backends", ["pybullet", "maniskill"])):
            one = Path(d) / f"{backend}.json"
            r = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench_sim.py"), f"backend={backend}",
                                f"episodes={n}", f"image_size={size}", f"out={one}"], cwd=ROOT,
                               capture_output=True, text=True)
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
    sys.exit(main(sys.argv[1:]))
