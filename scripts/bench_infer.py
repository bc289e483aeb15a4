"""Benchmark diagnosis latency: one pass (shared image prefix, KV cache) against six separate prompts, and
batched diagnosis (analyze_batch) against one grid at a time.

Run as:
    python scripts/bench_infer.py [model=DIR] [repeats=7] [batch=8] [out=outputs/bench_infer.json]
    python scripts/bench_infer.py dataset=outputs/demo_dataset split=test   # + evaluate.py's predictions

Tiny model on CPU by default (built on the fly if model is not given); the same script on a GPU
machine measures whatever checkpoint it is pointed at. Target (issue 5): one pass >= 4x faster.
With dataset, the bench's model predictions for a split (what labrobfail-evaluate runs) are timed with
batch_size 1 and `batch`, and must be equal.
The two modes alternate repeat by repeat, so a burst of load from other processes on a shared machine
hits both alike; wall and CPU seconds are both reported, with the load average before and after.
scripts/profile_infer.py shows where the one-pass time goes.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np

from labrobfail_vlm.config import ConfigError, cli_main, load_config, require_ints

DEFAULTS = """
model: null                    # model folder to measure; null = a tiny random model, built on the fly
repeats: 7                     # timed repeats of each mode (one pass, six prompts), alternating
batch: 8                       # grids per analyze_batch call in the batching rows
dataset: null                  # also time evaluate.py's predictions on this dataset (null = skip)
split: test                    # the dataset split for those predictions
out: outputs/bench_infer.json  # the JSON result
"""


def stats(ts: list[float]) -> dict[str, float]:
    return {
        "p50_s": round(float(np.percentile(ts, 50)), 4),
        "p95_s": round(float(np.percentile(ts, 95)), 4),
        "min_s": round(min(ts), 4),
    }


def evaluate_rows(fa: object, dataset: str, split: str, batch: int) -> dict[str, object]:
    """labrobfail-evaluate's model predictions for one split, one trajectory at a time and `batch` at a time."""
    from labrobfail_vlm.bench import evaluate as ev

    recs, traj = ev.load_split(dataset, split)
    times, preds = {}, {}
    for b in (1, batch):
        t = time.perf_counter()
        preds[b] = ev.model_predictions(fa, dataset, recs, traj, progress=False, batch_size=b)
        times[b] = time.perf_counter() - t
    assert preds[1] == preds[batch], "batched predictions differ"
    n = len({r["id"].rsplit("_", 1)[0] for r in recs})
    failed = sum(v != "None" for k, v in preds[1].items() if k.endswith("_Q3"))  # Q3 is a frame after "failed"
    return {
        "dataset": dataset,
        "split": split,
        "trajectories": n,
        "records": len(recs),
        "batch_1_s": round(times[1], 2),
        f"batch_{batch}_s": round(times[batch], 2),
        "speedup": round(times[1] / times[batch], 2),
        "failure_verdicts": failed,
    }


def main(argv: list[str]) -> int:
    a = load_config(DEFAULTS, argv)
    require_ints(a, ("repeats", "batch"))
    for key in ("model", "dataset"):
        if a[key] is not None and not isinstance(a[key], str):
            raise ConfigError(f"{key}: expected a folder path, got {a[key]!r}")
    import torch
    from PIL import Image

    from labrobfail_vlm.analyzer import DiagnosisRequest, FailureAnalyzer
    from labrobfail_vlm.io import write_report

    load_start = os.getloadavg()[0]
    model = a.model
    if model is None:
        from labrobfail_vlm.model.tiny import build_tiny

        model = str(build_tiny(Path(tempfile.mkdtemp()) / "tiny"))
    fa = FailureAnalyzer.from_pretrained(model)
    rng = np.random.default_rng(0)
    # grids of the size the model reads (its checkpoint's grid; the paper's 1536x768 for a model that names none)
    w, h = fa.grid.width, fa.grid.height
    grid = Image.fromarray(rng.integers(0, 255, (h, w, 3), dtype=np.uint8))
    task = "pick up the small beaker"
    wall: dict[str, list[float]] = {"one_pass": [], "six_prompts": []}
    cpu: dict[str, list[float]] = {"one_pass": [], "six_prompts": []}
    for one in (True, False):
        fa.answers(grid, task, one_pass=one)  # warm-up
    for _ in range(a.repeats):
        for name, one in (("one_pass", True), ("six_prompts", False)):
            t, c = time.perf_counter(), time.process_time()
            fa.answers(grid, task, one_pass=one)
            wall[name].append(time.perf_counter() - t)
            cpu[name].append(time.process_time() - c)
    rows = {k: {**stats(v), "cpu_p50_s": round(float(np.percentile(cpu[k], 50)), 4)} for k, v in wall.items()}
    # batching: the same number of distinct grids one at a time and in one analyze_batch call
    grids = [Image.fromarray(rng.integers(0, 255, (h, w, 3), dtype=np.uint8)) for _ in range(a.batch)]
    reqs = [DiagnosisRequest(g, task) for g in grids]
    fa.analyze_batch(reqs[:2])  # warm-up
    t = time.perf_counter()
    one_by_one = [fa.analyze(g, task) for g in grids]
    t_single = time.perf_counter() - t
    t = time.perf_counter()
    together = fa.analyze_batch(reqs, max_batch=a.batch)
    t_batch = time.perf_counter() - t
    assert [d.raw for d in together] == [d.raw for d in one_by_one], "batched answers differ"
    res = {
        "model": "tiny (random)" if a.model is None else a.model,
        "grid": f"{w}x{h}",
        "device": str(next(fa.model.parameters()).device),
        "threads": torch.get_num_threads(),
        "rows": rows,
        "speedup_one_pass": round(rows["six_prompts"]["p50_s"] / rows["one_pass"]["p50_s"], 2),
        "speedup_one_pass_cpu": round(rows["six_prompts"]["cpu_p50_s"] / rows["one_pass"]["cpu_p50_s"], 2),
        "target": 4.0,
        "q2": one_by_one[0].raw["Q2"],
        "batch": {
            "grids": a.batch,
            "one_at_a_time_s_per_grid": round(t_single / a.batch, 4),
            "analyze_batch_s_per_grid": round(t_batch / a.batch, 4),
            "speedup": round(t_single / t_batch, 2),
        },
        "load_average": [round(load_start, 2), round(os.getloadavg()[0], 2)],
    }
    if a.dataset:
        res["evaluate"] = evaluate_rows(fa, a.dataset, str(a.split), a.batch)
        res["load_average"][1] = round(os.getloadavg()[0], 2)
    return write_report(a.out, res)


if __name__ == "__main__":
    cli_main(main, __doc__)
