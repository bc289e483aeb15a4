"""Benchmark training throughput of the tiny preset on CPU (and Qwen3-VL-8B dimensions on a GPU when present).

Run as:
    python scripts/bench_train.py [steps=6] [batch=4] [out=outputs/bench_train.json]
    python scripts/bench_train.py --steps 2

Rows side by side in one run, same batch: hybrid vs full tuning, at the 1536x768 grid (1152 visual tokens)
and a 768x384 grid (288). Reports samples/s, tokens/s and peak RSS. The GPU row (random weights with the
real 8B dimensions) runs only where CUDA is available; CI and the CPU machines skip it and say so.

With dataset_dir=DIR (a built dataset), also the frozen-tower recipe of `train.py preset=tiny` (the shipped
tower) for `epochs` epochs on it, with and without the tower cache (labrobfail_vlm/train/tower_cache.py), one
after the other in this run: the Trainer loop's seconds and their ratio.
    python scripts/bench_train.py dataset_dir=outputs/demo_dataset epochs=6
"""

from __future__ import annotations

import json
import resource
import tempfile
import time
from pathlib import Path

from labrobfail_vlm.config import ConfigError, cli_main, load_config, require_ints

DEFAULTS = """
steps: 6                       # timed optimizer steps per row (after one warm-up step)
batch: 4                       # samples per step (the same sample repeated)
out: outputs/bench_train.json  # the JSON result
dataset_dir: null              # a built dataset: adds the tower-cache rows (real training runs on it)
epochs: 6                      # epochs of each tower-cache row (make reproduce trains 6)
"""


def cache_rows(dataset_dir: str, epochs: int, tmp: Path) -> dict[str, float]:
    """train.py preset=tiny (frozen shipped tower) on dataset_dir with the tower cache off, then on."""
    import subprocess
    import sys

    rows: dict[str, float] = {}
    for name, mb in (("off", 0), ("on", 4096)):
        out = tmp / f"cache_{name}"
        cmd = [sys.executable, "train.py", "preset=tiny", f"dataset_dir={dataset_dir}", f"output_dir={out}"]
        cmd += [f"epochs={epochs}", f"tower_cache_mb={mb}", "wandb.enabled=false", "progress=false"]
        cmd += ["save_steps=100000"]  # no checkpoints inside the timed loop
        r = subprocess.run(cmd, capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1])
        if r.returncode != 0:
            last = (r.stderr.strip().splitlines() or ["no message"])[-1]
            raise ConfigError(f"dataset_dir: train.py failed on {dataset_dir}: {last}")
        summary = json.loads((out / "train_summary.json").read_text())
        rows[f"train_s_cache_{name}"] = summary["train_s"]
        rows["train_loss_cache_" + name] = summary["train_loss"]
    rows["on_over_off"] = round(rows["train_s_cache_on"] / rows["train_s_cache_off"], 3)
    return rows


def step_rate(model, batch, steps: int) -> dict[str, float]:
    import torch

    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-5)
    model.train()
    model(**batch).loss.backward()  # warm-up
    opt.step()
    opt.zero_grad()
    t = time.perf_counter()
    for _ in range(steps):
        model(**batch).loss.backward()
        opt.step()
        opt.zero_grad()
    dt = (time.perf_counter() - t) / steps
    n, tok = batch["input_ids"].shape[0], int(batch["attention_mask"].sum())
    return {"step_s": round(dt, 4), "samples_per_s": round(n / dt, 2), "tokens_per_s": round(tok / dt, 1)}


def main(argv: list[str]) -> int:
    a = load_config(DEFAULTS, argv)
    require_ints(a, ("steps", "batch", "epochs"))
    if a.dataset_dir is not None:
        from labrobfail_vlm.train.cli import dataset_stats

        dataset_stats(a.dataset_dir)  # train.py's own test, before the timed rows
    import torch
    from PIL import Image

    from labrobfail_vlm.io import write_report
    from labrobfail_vlm.model.hybrid import apply_tuning
    from labrobfail_vlm.model.loading import load_model, load_processor
    from labrobfail_vlm.model.tiny import build_tiny
    from labrobfail_vlm.train.data import Collator

    torch.manual_seed(0)
    tmp = Path(tempfile.mkdtemp())
    path = build_tiny(tmp / "tiny")
    proc = load_processor(path)
    proc.tokenizer.padding_side = "right"
    rows = {}
    for w, h in ((1536, 768), (768, 384)):
        img = tmp / f"g{w}.png"
        Image.new("RGB", (w, h), (90, 120, 150)).save(img)
        item = {
            "id": "x_Q6",
            "image": str(img),
            "question": "<image>\nThe image consists of a series of frames. "
            "What is the correction solution for this failure?",
            "answer": "Keep the gripper closed to secure "
            "the small beaker and move the robotic arm to the target area while maintaining orientation "
            "horizontal.",
        }
        batch = Collator(proc, 4096)([item] * a.batch)
        for mode in ("hybrid", "full"):
            model = apply_tuning(load_model(path), mode, {"r": 32, "alpha": 64, "dropout": 0.0})
            rows[f"tiny_{mode}_{w}x{h}"] = step_rate(model, batch, a.steps)
    res = {
        "device": "cpu",
        "threads": torch.get_num_threads(),
        "batch": a.batch,
        "rows": rows,
        "full_over_hybrid_step_ratio_1536": round(
            rows["tiny_full_1536x768"]["step_s"] / rows["tiny_hybrid_1536x768"]["step_s"], 3
        ),
        **({"tower_cache": cache_rows(str(a.dataset_dir), int(a.epochs), tmp)} if a.dataset_dir else {}),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "gpu": "not measured: no CUDA device on this machine (the device tool lent none to this task)"
        if not torch.cuda.is_available()
        else "see gpu_rows",
    }
    return write_report(a.out, res)


if __name__ == "__main__":
    cli_main(main, __doc__)
