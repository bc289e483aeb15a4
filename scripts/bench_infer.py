"""Benchmark diagnosis latency: one pass (shared image prefix, KV cache) against six separate prompts.

Run as:
    python scripts/bench_infer.py [--model DIR] [--repeats 5] [--out outputs/bench_infer.json]

Tiny model on CPU by default (built on the fly if --model is not given); the same script on a GPU
machine measures whatever checkpoint it is pointed at. Target (issue 5): one pass >= 4x faster.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--model", default=None)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default="outputs/bench_infer.json")
    a = ap.parse_args()
    import torch
    from PIL import Image

    from labrobfail_vlm.analyzer import FailureAnalyzer
    from labrobfail_vlm.io import atomic_write_json

    model = a.model
    if model is None:
        from labrobfail_vlm.model.tiny import build_tiny
        model = str(build_tiny(Path(tempfile.mkdtemp()) / "tiny"))
    fa = FailureAnalyzer.from_pretrained(model)
    rng = np.random.default_rng(0)
    grid = Image.fromarray(rng.integers(0, 255, (768, 1536, 3), dtype=np.uint8))
    rows = {}
    for name, one in (("one_pass", True), ("six_prompts", False)):
        fa.answers(grid, "pick up the small beaker", one_pass=one)  # warm-up
        ts = []
        for _ in range(a.repeats):
            t = time.perf_counter()
            fa.answers(grid, "pick up the small beaker", one_pass=one)
            ts.append(time.perf_counter() - t)
        rows[name] = {"p50_s": round(float(np.percentile(ts, 50)), 4), "p95_s": round(float(np.percentile(ts, 95)), 4)}
    res = {"model": "tiny (random)" if a.model is None else a.model, "grid": "1536x768",
           "device": str(next(fa.model.parameters()).device), "threads": torch.get_num_threads(), "rows": rows,
           "speedup_one_pass": round(rows["six_prompts"]["p50_s"] / rows["one_pass"]["p50_s"], 2), "target": 4.0}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(Path(a.out), res)
    print(json.dumps(res))


if __name__ == "__main__":
    main()
