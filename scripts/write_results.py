"""Write docs/RESULTS.md from a `make reproduce` run: the bench tables in the paper's layout, data and grid sizes,
targets, per-type failure-detection recall, prefix accuracy, timings and the learning curve.

Run as:
    python scripts/write_results.py outputs/reproduce docs/RESULTS.md

Reads <run>/dataset/stats.json, <run>/train/{train_summary,progress,learning_curve}.json,
<run>/train/final/eval_<split>/results.json and <run>/timeline.txt (one "<step> <unix seconds>" line per step).
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from labrobfail_vlm.config import ConfigError, cli_main  # noqa: E402

# The targets (LabRobFail-Bench, exact metrics of the evaluator): (split, metric) -> at least.
TARGETS = {("test", "q2"): 91, ("test", "q3"): 78, ("test", "q4"): 84, ("test", "q5"): 74, ("test", "rougeL"): 0.76,
           ("both", "q2"): 75, ("both", "q3"): 50, ("both", "q5"): 55}
SPLIT_TITLES = {"test": "Seen (test split)", "object": "Unseen objects", "scene": "Unseen scene",
                "both": "Unseen objects and scene"}


def _load(path: Path) -> Any:
    if not path.is_file():
        raise ConfigError(f"results: {path} is missing (run `make reproduce` first)")
    return json.loads(path.read_text())


def _metric(res: dict[str, Any], key: str) -> float | None:
    return res["q6"][key] if key == "rougeL" else res[key]


def main(argv: list[str]) -> int:
    from labrobfail_vlm.bench.report import PAPER_ROWS, PAPER_UNSEEN_ROWS, markdown, row

    if len(argv) != 2:
        raise ConfigError("usage: write_results.py RUN_DIR OUT_MD")
    run, out = Path(argv[0]), Path(argv[1])
    stats = _load(run / "dataset" / "stats.json")
    summary = _load(run / "train" / "train_summary.json")
    progress = _load(run / "train" / "progress.json")
    evals = {s: _load(run / "train" / "final" / f"eval_{s}" / "results.json") for s in SPLIT_TITLES}
    prefix_file = run / "train" / "final" / "eval_prefix" / "results.json"
    prefix = _load(prefix_file) if prefix_file.is_file() else None
    stamps = [line.split() for line in (run / "timeline.txt").read_text().splitlines() if line.strip()]
    times = {name: int(t) for name, t in stamps}
    steps = [(a[0], int(b[1]) - int(a[1])) for a, b in zip(stamps, stamps[1:])]
    total_min = (int(stamps[-1][1]) - int(stamps[0][1])) / 60 if len(stamps) > 1 else None
    grid = stats["grid"]
    lines = ["# LabRobFail-Bench results of the from-scratch CPU recipe", "",
             "Made by `make reproduce` (2 CPU cores, no GPU, no pretrained weights): PyBullet generation of seen and",
             "unseen data, the dataset, the tiny Qwen3-VL trained from random initialisation (`preset=tiny`), the",
             "bench on every split with the majority and blind baselines, and the learning curve. This file and",
             "`docs/learning_curve.png` are written by `scripts/write_results.py` from that run; nothing is edited by",
             "hand.", ""]
    if total_min is not None:
        lines += [f"End to end: **{total_min:.1f} min** wall-clock. Steps: "
                  + ", ".join(f"{n} {s / 60:.1f} min" for n, s in steps) + ".", ""]
    params = sum(summary["trainable_parameters"].values())
    lines += ["## Data and model", "",
              f"- Trajectories: {stats['trajectories_kept']} kept of {stats['trajectories_in']} "
              f"({stats['by_outcome']['success']} success, {stats['by_outcome']['failure']} failure); split sizes "
              "(trajectories): " + ", ".join(f"{k} {v['trajectories']}" for k, v in stats["splits"].items()) + ".",
              f"- Grid: {grid['width']}x{grid['height']} px, {grid['max_frames']} keyframes x 2 views, "
              f"{grid['columns']} time steps per band ({(grid['width'] // 32) * (grid['height'] // 32)} visual tokens);"
              f" prefix grids per trajectory: {stats.get('prefix', {}).get('cuts', 0)}.",
              f"- Model: Qwen3-VL architecture at tiny size, {params / 1e6:.2f} M parameters, all trained; "
              f"{summary['global_step']} optimizer steps, {progress[-1]['examples'] if progress else '?'} training "
              f"records, {progress[-1]['wall_s'] / 60 if progress else 0:.1f} min of training.", ""]
    for split, title in SPLIT_TITLES.items():
        res = evals[split]
        rows = {"tiny LabRobFail-VLM (ours, free Q6)": row(res),
                **{f"tiny LabRobFail-VLM (ours, {k.split(', ')[-1]})" if k.endswith("Q6 template") else k: row(v)
                   for k, v in res["baselines"].items()}}
        rows.update({"LabRobFail-VLM (paper, 8B)": PAPER_UNSEEN_ROWS[split]} if split in PAPER_UNSEEN_ROWS else
                    {k: v for k, v in PAPER_ROWS.items()})
        lines += [markdown(rows, f"{title}: {res['records']} records").replace("### ", "## "), ""]
    lines += ["## Targets", "", "| split | metric | target | reached | met |", "|---|---|---|---|---|"]
    for (split, key), want in TARGETS.items():
        got = _metric(evals[split], key)
        lines.append(f"| {split} | {key} | {want} | {got} | {'yes' if got is not None and got >= want else 'no'} |")
    blind = evals["test"]["baselines"].get("blind (grey grid)", {}).get("q2")
    major = evals["test"]["baselines"].get("majority class", {}).get("q2")
    lines += ["", f"Blind baseline (grey grid, same model) on seen Q2: {blind}; majority class: {major}.", ""]
    lines += ["## Failure detection (Q2) per failure type, seen test split", "", "| type | Q2 recall | n |",
              "|---|---|---|"]
    traj = {t["trajectory"]: t for t in json.loads((run / "dataset" / "trajectories.json").read_text())}
    counts: dict[str, int] = {}
    for t in traj.values():
        if t.get("split") == "test" and "prefix_of" not in t and not t["success"]:
            counts[t["failure_type"]] = counts.get(t["failure_type"], 0) + 1
    for key, dims in sorted(evals["test"]["breakdown"].items()):
        if key.startswith("type:") and "Q2" in dims:
            name = key.split(":", 1)[1]
            lines.append(f"| {name} | {dims['Q2']:.1f} | {counts.get(name, '—') if name != 'success' else '—'} |")
    if prefix is not None:
        lines += ["", "## Prefix grids (online supervision: the first k keyframes)", "",
                  f"Seen test prefixes, {prefix['records']} records: Q2 (has a failure shown up yet) "
                  f"**{prefix['q2']}**, Q3 (its frame, or None) **{prefix['q3']}**; blind Q2 "
                  f"{prefix['baselines'].get('blind (grey grid)', {}).get('q2')}, majority Q2 "
                  f"{prefix['baselines'].get('majority class', {}).get('q2')}."]
    curve = run / "train" / "learning_curve.png"
    if curve.is_file():
        shutil.copyfile(curve, out.parent / "learning_curve.png")
        lines += ["", "## Learning curve (validation split)", "", "![learning curve](learning_curve.png)"]
    lines += ["", f"Run timeline (unix seconds): {json.dumps(times)}", ""]
    from labrobfail_vlm.io import atomic_write_bytes
    atomic_write_bytes(out, "\n".join(lines).encode())
    print(out)
    return 0


if __name__ == "__main__":
    cli_main(main)
