"""Failure detection (Q2) as a score: AUROC, AUPRC, expected calibration error and a reliability diagram.

One score per trajectory, P(failure): the analyzer's softmax over its two admissible Q2 replies, a constant for the
majority class (the training failure rate), or, for a predictions file without `p_failure`, the hard reply (1 for
a failure, 0 otherwise; `score` says "hard", and the AUROC of a hard reply is its balanced accuracy).
AUROC and AUPRC are scikit-learn's `roc_auc_score` and `average_precision_score`; ECE uses ten equal-width bins,
sum over bins of (bin size / N) * |failure rate in the bin - mean score in the bin|.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

ECE_BINS = 10


def detection_metrics(y: Sequence[bool], p: Sequence[float], score: str = "probability") -> dict[str, Any]:
    """`y`: a failure happened, `p`: its score, one pair per trajectory. AUROC/AUPRC are None when the split holds
    one class only (both are undefined there)."""
    from sklearn.metrics import average_precision_score, roc_auc_score

    yt, pt = np.asarray(y, dtype=bool), np.asarray(p, dtype=np.float64)
    both = 0 < int(yt.sum()) < len(yt)
    edges = np.round(np.linspace(0.0, 1.0, ECE_BINS + 1), 10)  # linspace's 0.30000000000000004 put 0.3 one bin low
    idx = np.clip(np.digitize(pt, edges[1:-1]), 0, ECE_BINS - 1)
    bins = []
    ece = 0.0
    for b in range(ECE_BINS):
        m = idx == b
        if not m.any():
            continue
        conf, rate = float(pt[m].mean()), float(yt[m].mean())
        ece += m.sum() / len(yt) * abs(rate - conf)
        bins.append(
            {
                "lo": round(float(edges[b]), 2),
                "hi": round(float(edges[b + 1]), 2),
                "n": int(m.sum()),
                "mean_score": round(conf, 4),
                "failure_rate": round(rate, 4),
            }
        )
    return {
        "auroc": round(float(roc_auc_score(yt, pt)), 4) if both else None,
        "auprc": round(float(average_precision_score(yt, pt)), 4) if both else None,
        "ece": round(float(ece), 4) if len(yt) else None,
        "trajectories": int(len(yt)),
        "failures": int(yt.sum()),
        "score": score,
        "bins": bins,
    }


def reliability_png(curves: dict[str, dict[str, Any]], title: str, path: Path) -> None:
    """One reliability curve per method (mean score against observed failure rate per bin) beside the diagonal,
    with the share of trajectories per bin under it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from labrobfail_vlm.io import save_figure

    fig, (ax, hx) = plt.subplots(2, 1, figsize=(5.2, 6.2), height_ratios=[3, 1], sharex=True)
    ax.plot([0, 1], [0, 1], ls="--", c="grey", lw=1, label="perfectly calibrated")
    width = 1.0 / ECE_BINS / (len(curves) + 1)
    for k, (name, m) in enumerate(curves.items()):
        xs = [b["mean_score"] for b in m["bins"]]
        label = f"{name} (AUROC {m['auroc'] if m['auroc'] is not None else '—'}, ECE {m['ece']})"
        ax.plot(xs, [b["failure_rate"] for b in m["bins"]], marker="o", label=label)
        n = max(1, m["trajectories"])
        hx.bar(
            [b["lo"] + (k + 0.5) * width for b in m["bins"]], [b["n"] / n for b in m["bins"]], width=width, label=name
        )
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_ylabel("observed failure rate")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7, loc="upper left")
    hx.set_xlabel("P(failure)")
    hx.set_ylabel("share")
    save_figure(fig, path, dpi=100)


def accuracy_threshold(y: Sequence[bool], p: Sequence[float]) -> float:
    """The operating point on P(failure) with the best Q2 accuracy on (y, p): "failed" when p >= threshold. The
    candidates are 0.5 and the midpoints between neighbouring distinct scores (a threshold between two scores
    scores like any other there); ties go to the candidate nearest 0.5, the decoder's own argmax."""
    yt, pt = np.asarray(y, dtype=bool), np.asarray(p, dtype=np.float64)
    if not len(yt):
        raise ValueError("accuracy_threshold: no scored trajectories")
    s = np.unique(pt)
    cands = np.unique(np.concatenate([[0.5], (s[:-1] + s[1:]) / 2]))
    cands = cands[(cands > 0.0) & (cands < 1.0)]
    acc = ((pt[None, :] >= cands[:, None]) == yt[None, :]).mean(axis=1)
    best = np.flatnonzero(acc >= acc.max() - 1e-12)
    return float(cands[best[np.argmin(np.abs(cands[best] - 0.5))]])
