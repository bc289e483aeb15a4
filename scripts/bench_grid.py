"""Benchmark the keyframe-grid builder (16 keyframes x 2 views of 224x224 -> 1536x768) and write JSON.

Run as:
    python scripts/bench_grid.py [repeats=200] [out=outputs/bench_grid.json]
    python scripts/bench_grid.py --repeats 20

Rows side by side in one run: with the temporal index, without it, and a prefix grid; p50/p95 in ms.
Target (issue 3): a 1536x768 grid in at most 10 ms.
"""

from __future__ import annotations

import platform
import time
from pathlib import Path

import numpy as np

from labrobfail_vlm.config import ConfigError, cli_main, load_config
from labrobfail_vlm.grid import GridConfig, build_grid
from labrobfail_vlm.io import write_report

DEFAULTS = """
repeats: 200                  # timed builds per row (after one warm-up build)
out: outputs/bench_grid.json  # the JSON result
"""


def timed(fn, repeats: int) -> dict[str, float]:
    fn()  # warm-up (font cache)
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(1000 * (time.perf_counter() - t))
    return {"p50_ms": round(float(np.percentile(ts, 50)), 3), "p95_ms": round(float(np.percentile(ts, 95)), 3)}


def main(argv: list[str]) -> int:
    cfg = load_config(DEFAULTS, argv)
    repeats = cfg.repeats
    if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 1:
        raise ConfigError(f"repeats: expected an integer >= 1, got {repeats!r}")
    out = Path(str(cfg.out))
    rng = np.random.default_rng(0)
    frames = [[rng.integers(0, 255, (224, 224, 3), dtype=np.uint8) for _ in range(16)] for _ in range(2)]
    rows = {
        "with_index": timed(lambda: build_grid(frames, GridConfig()), repeats),
        "without_index": timed(lambda: build_grid(frames, GridConfig(draw_index=False)), repeats),
        "prefix_8_of_16": timed(lambda: build_grid(frames, GridConfig(), visible=8), repeats),
    }
    res = {
        "grid": "1536x768, 16 keyframes x 2 views of 224x224",
        "repeats": repeats,
        "rows": rows,
        "index_overhead_ratio": round(rows["with_index"]["p50_ms"] / rows["without_index"]["p50_ms"], 3),
        "target_ms": 10.0,
        "meets_target": rows["with_index"]["p95_ms"] <= 10.0,
        "machine": platform.processor() or platform.machine(),
    }
    return write_report(out, res)


if __name__ == "__main__":
    cli_main(main, __doc__)
