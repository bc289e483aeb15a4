"""Benchmark LabRobFail-Sim throughput on this machine and write JSON.

Run as:
    python scripts/bench_sim.py [episodes=16] [out=outputs/bench_sim.json]

Measures, on the same scenario mix and seeds, side by side in one run:
physics-only episodes/hour/core, with two 224x224 views rendered at keyframes,
end to end into shards with 1 worker and with 2 workers (speed-up = ratio),
and peak memory per worker process.
"""

from __future__ import annotations

import json
import resource
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omegaconf import OmegaConf  # noqa: E402

from data.generate import generate, load_config, pair_seed, scenario_order  # noqa: E402
from labrobfail_vlm.io import atomic_write_json  # noqa: E402
from sim_backends.failure_generator import run_pair  # noqa: E402
from sim_backends.registry import make_backend  # noqa: E402


def per_hour(n: int, seconds: float) -> float:
    return round(3600.0 * n / seconds, 1)


def in_process(render: bool, pairs: int) -> float:
    src = make_backend("pybullet", render=render)
    # The generator's own pair plan (seed 0), so these rows run the same scenarios as the end-to-end ones.
    order = scenario_order(src.scenarios(), 0, pairs)
    t = time.perf_counter()
    for j, scenario in enumerate(order):
        run_pair(src, scenario, pair_seed(0, j), "seen")
    dt = time.perf_counter() - t
    src.close()
    return per_hour(2 * pairs, dt)


def end_to_end(workers: int, n: int) -> float:
    with tempfile.TemporaryDirectory() as d:
        cfg = load_config([f"out_dir={d}/s", f"num_episodes={n}", f"workers={workers}", "progress=false",
                           "episodes_per_shard=2", "seed=0"])
        t = time.perf_counter()
        generate(cfg)
        return time.perf_counter() - t


def main(argv: list[str]) -> int:
    args = OmegaConf.from_dotlist(argv)
    n = int(args.get("episodes", 24))
    out = Path(args.get("out", "outputs/bench_sim.json"))
    physics = in_process(False, n // 2)
    rendered = in_process(True, n // 2)
    t1 = end_to_end(1, n)
    t2 = end_to_end(2, n)
    res = {
        "episodes": n,
        "scenario_mix": "round-robin over all scenarios (short, medium and long horizon)",
        "physics_only_episodes_per_hour_per_core": physics,
        "rendered_2x224_episodes_per_hour_per_core": rendered,
        "end_to_end_episodes_per_hour_per_core": per_hour(n, t1),
        "end_to_end_2_workers_episodes_per_hour": per_hour(n, t2),
        "speedup_2_workers": round(t1 / t2, 2),
        "peak_rss_mb_main_process": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "peak_rss_mb_worker": round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024, 1),
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out, res, indent=2)
    print(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
