"""Dataset plots (matplotlib, Agg): horizon distribution, success vs failure per task, types by category."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from labrobfail_vlm.io import save_figure  # noqa: E402
from labrobfail_vlm.taxonomy import FAILURE_TYPES, HORIZONS, Category  # noqa: E402

COLORS = {
    Category.SAFETY: "#d62728",
    Category.LOGIC: "#9467bd",
    Category.MOTION: "#1f77b4",
    Category.GRASPING: "#ff7f0e",
    Category.PERCEPTION: "#2ca02c",
}


def write_plots(traj: list[dict[str, Any]], out: Path) -> None:
    # Horizon distribution
    h = Counter(t["horizon"] for t in traj)
    fig, ax = plt.subplots(figsize=(4.5, 3.2))
    ax.bar(list(HORIZONS), [h.get(k, 0) for k in HORIZONS], color=["#8ecae6", "#219ebc", "#023047"])
    ax.set_title("Trajectories by task horizon")
    ax.set_ylabel("trajectories")
    save_figure(fig, out / "horizon_distribution.png")

    # Success vs failure per task
    tasks = sorted({t["scenario"] for t in traj})
    ok = Counter(t["scenario"] for t in traj if t["success"])
    bad = Counter(t["scenario"] for t in traj if not t["success"])
    fig, ax = plt.subplots(figsize=(8, 0.28 * len(tasks) + 1.4))
    ax.barh(tasks, [ok[t] for t in tasks], color="#2a9d8f", label="success")
    ax.barh(tasks, [bad[t] for t in tasks], left=[ok[t] for t in tasks], color="#e76f51", label="failure")
    ax.invert_yaxis()
    ax.set_xlabel("trajectories")
    ax.set_title("Success vs failure per task")
    ax.legend(loc="lower right")
    save_figure(fig, out / "success_failure_per_task.png")

    # The 11 types grouped into the 5 categories
    ft = Counter(t["failure_type"] for t in traj if not t["success"])
    order = sorted(FAILURE_TYPES.values(), key=lambda f: (-int(f.category), f.name))
    fig, ax = plt.subplots(figsize=(8, 4.2))
    ax.barh([f.name for f in order], [ft.get(f.name, 0) for f in order], color=[COLORS[f.category] for f in order])
    ax.invert_yaxis()
    for c in Category:
        ax.bar(0, 0, color=COLORS[c], label=f"{c.title} ({sum(ft.get(f.name, 0) for f in order if f.category == c)})")
    ax.legend(loc="lower right", fontsize=8)
    ax.set_xlabel("failure trajectories")
    ax.set_title("Failure types by category")
    save_figure(fig, out / "failure_types_by_category.png")
