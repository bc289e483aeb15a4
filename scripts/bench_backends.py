"""Benchmark LabRobFail-Sim throughput per simulator backend and write the comparison table.

Run as:
    python scripts/bench_backends.py [backends=[pybullet,maniskill]] [episodes=28] [out=outputs/bench_backends.json]

Each backend is measured in a child process of its own (so peak memory is its own), on its own scenario
mix (round-robin over all its scenarios, seed 0, as scripts/generate.py plans it): physics-only
episodes/hour/core, with two 224x224 views rendered at keyframes, end to end into shards with 1 worker
and with 2 workers (speed-up = ratio), peak memory. Writes `out` (backend -> the keys scripts/bench_sim.py
writes, plus `backend`) and the same as a Markdown table next to it (`.md`).
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from omegaconf import OmegaConf  # noqa: E402

from labrobfail_vlm.io import atomic_write_bytes, atomic_write_json  # noqa: E402

ROWS = [  # (key, label) of the table, in order
    ("physics_only_episodes_per_hour_per_core", "physics only, episodes/h/core"),
    ("rendered_2x224_episodes_per_hour_per_core", "2 views 224x224, episodes/h/core"),
    ("end_to_end_episodes_per_hour_per_core", "end to end to shards, 1 worker, episodes/h"),
    ("end_to_end_2_workers_episodes_per_hour", "end to end to shards, 2 workers, episodes/h"),
    ("speedup_2_workers", "speed-up with 2 workers"),
    ("peak_rss_mb_main_process", "peak RSS, in-process runs (MB)"),
    ("peak_rss_mb_worker", "peak RSS, a worker (MB)"),
    ("scenarios", "scenarios in the mix"),
]


def per_hour(n: int, seconds: float) -> float:
    return round(3600.0 * n / seconds, 1)


def in_process(backend: str, render: bool, pairs: int) -> float:
    from data.generate import pair_seed, scenario_order
    from sim_backends.failure_generator import run_pair
    from sim_backends.registry import make_backend

    src = make_backend(backend, render=render)
    order = scenario_order(src.scenarios(), 0, pairs)  # the generator's own pair plan
    t = time.perf_counter()
    for j, scenario in enumerate(order):
        run_pair(src, scenario, pair_seed(0, j), "seen")
    dt = time.perf_counter() - t
    src.close()
    return per_hour(2 * pairs, dt)


def end_to_end(backend: str, workers: int, n: int) -> float:
    from data.generate import generate, load_config

    with tempfile.TemporaryDirectory() as d:
        cfg = load_config([f"backend={backend}", f"out_dir={d}/s", f"num_episodes={n}", f"workers={workers}",
                           "progress=false", "episodes_per_shard=2", "seed=0"])
        t = time.perf_counter()
        generate(cfg)
        return time.perf_counter() - t


def measure(backend: str, n: int) -> dict:
    from sim_backends.registry import backend_spec

    physics = in_process(backend, False, n // 2)
    rendered = in_process(backend, True, n // 2)
    t1 = end_to_end(backend, 1, n)
    t2 = end_to_end(backend, 2, n)
    return {
        "backend": backend,
        "episodes": n,
        "scenario_mix": "round-robin over all of the backend's scenarios (seed 0)",
        "scenarios": len(backend_spec(backend).cls.list_scenarios()),
        "physics_only_episodes_per_hour_per_core": physics,
        "rendered_2x224_episodes_per_hour_per_core": rendered,
        "end_to_end_episodes_per_hour_per_core": per_hour(n, t1),
        "end_to_end_2_workers_episodes_per_hour": per_hour(n, t2),
        "speedup_2_workers": round(t1 / t2, 2),
        "peak_rss_mb_main_process": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "peak_rss_mb_worker": round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024, 1),
    }


def table(results: dict[str, dict]) -> str:
    names = list(results)
    lines = ["| | " + " | ".join(names) + " |", "| --- |" + " --- |" * len(names)]
    for key, label in ROWS:
        lines.append(f"| {label} | " + " | ".join(str(results[b].get(key, "")) for b in names) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> int:
    args = OmegaConf.from_dotlist(argv)
    n = int(args.get("episodes", 28))
    if args.get("_one"):  # the child: one backend, JSON on stdout
        print(json.dumps(measure(str(args["_one"]), n)))
        return 0
    out = Path(args.get("out", "outputs/bench_backends.json"))
    results = {}
    for backend in list(args.get("backends", ["pybullet", "maniskill"])):
        r = subprocess.run([sys.executable, __file__, f"_one={backend}", f"episodes={n}"], cwd=ROOT,
                           capture_output=True, text=True)
        if r.returncode != 0:
            tail = (r.stderr.strip().splitlines() or ["no output"])[-1]
            print(f"error: {backend}: {tail}", file=sys.stderr)
            return 2
        results[backend] = json.loads(r.stdout.strip().splitlines()[-1])
    atomic_write_json(out, results, indent=2)
    atomic_write_bytes(out.with_suffix(".md"), table(results).encode())
    print(table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
