"""Learning curve of a training run: each checkpoint's Q2-Q5 accuracy against training examples and CPU minutes.

Run as:
    python scripts/learning_curve.py run_dir=outputs/reproduce/train dataset_dir=outputs/reproduce/dataset
    python scripts/learning_curve.py run_dir=... dataset_dir=... split=test out=docs/learning_curve.png

Reads run_dir/checkpoint-N (kept with save_total_limit=null) and run_dir/progress.json (written by train.py at
every checkpoint: records seen, wall and CPU seconds). Writes <out>.json beside the PNG. Defaults:
configs/learning_curve.yaml.
"""

from __future__ import annotations

import gc
import json
import re
from pathlib import Path

from labrobfail_vlm.config import ConfigError, cli_main, load_config

DIMS = ("Q2", "Q3", "Q4", "Q5")


def main(argv: list[str]) -> int:
    from tqdm import tqdm

    from labrobfail_vlm import questions as Q
    from labrobfail_vlm.analyzer import FailureAnalyzer
    from labrobfail_vlm.bench import evaluate as ev
    from labrobfail_vlm.io import atomic_write_json, save_figure
    from labrobfail_vlm.train.tower_cache import check_cache_mb, inference_cache

    cfg = load_config("learning_curve.yaml", argv)
    run = Path(str(cfg.run_dir))
    check_cache_mb(cfg.tower_cache_mb)
    progress = run / "progress.json"
    if not progress.is_file():
        raise ConfigError(f"run_dir: {run} has no progress.json (a run of train.py with checkpoints)")
    rows = {r["step"]: r for r in json.loads(progress.read_text())}
    ckpts = sorted(
        (int(m.group(1)), p) for p in run.glob("checkpoint-*") if (m := re.fullmatch(r"checkpoint-(\d+)", p.name))
    )
    ckpts = [(s, p) for s, p in ckpts if s in rows]
    if not ckpts:
        raise ConfigError(f"run_dir: no checkpoint-N in {run} matches progress.json (train with save_total_limit=null)")
    recs, traj = ev.load_split(cfg.dataset_dir, cfg.split)
    recs = [r for r in recs if Q.dim_of(r["id"]) in DIMS]
    points, cache = [], None
    for step, path in tqdm(ckpts, desc="checkpoints", disable=not cfg.progress):
        analyzer = FailureAnalyzer.from_pretrained(path)
        # a frozen tower's checkpoints share its weights: each grid is encoded once for all of them
        cache = inference_cache(analyzer.model, float(cfg.tower_cache_mb), previous=cache)
        res = ev.score(recs, ev.model_predictions(analyzer, cfg.dataset_dir, recs, traj, progress=False), traj)
        del analyzer
        gc.collect()  # a cached tower and its model refer to each other: free the checkpoint before the next loads
        points.append({**rows[step], **{d.lower(): res[d.lower()] for d in DIMS}})
    out = Path(str(cfg.out or run / "learning_curve.png"))
    atomic_write_json(out.with_suffix(".json"), {"split": cfg.split, "run_dir": str(run), "points": points})

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
    for ax, key, label in (
        (axes[0], "examples", "training examples (records)"),
        (axes[1], "cpu_s", "CPU minutes (all threads)"),
    ):
        for d in DIMS:
            xs = [p[key] / (60 if key == "cpu_s" else 1) for p in points]
            ax.plot(xs, [p[d.lower()] for p in points], marker="o", label=f"{d} {Q.DIMENSION_NAMES[d]}")
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(f"accuracy on {cfg.split} (%)")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"LabRobFail-VLM learning curve ({run.name})")
    save_figure(fig, out)
    print(json.dumps(points[-1]))
    return 0


if __name__ == "__main__":
    cli_main(main, __doc__)
