"""Bench reports: the Markdown tables in the paper's layout, confusion-matrix PNGs, the paper's reference rows.

Two tables per split. The paper-comparable one takes Q1 and Q2 over all trajectories and Q3-Q6 over the failed
trajectories only (`failure_only`), and sits beside the paper's rows. The all-trajectory one (Q3-Q6 over successes
too, whose answer is "None") is the project's own and carries no paper rows: its numbers are not the paper's.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

# Published results (paper, main table, seen environments): Q1-Q5 accuracy %, BLEU-1..4, ROUGE-L.
PAPER_ROWS: dict[str, list[float]] = {
    "Qwen3-VL-8B (paper)": [47.45, 59.50, 5.59, 47.84, 35.88, 0.2594, 0.1249, 0.0626, 0.0366, 0.2976],
    "LLaVA-1.6-13B (paper)": [35.80, 52.96, 13.24, 33.53, 31.18, 0.2278, 0.0999, 0.0506, 0.0255, 0.2598],
    "InternVL2.5-8B (paper)": [28.10, 47.04, 12.35, 18.24, 42.06, 0.1174, 0.0507, 0.0258, 0.0149, 0.1430],
    "DeepSeek-VL2-small (paper)": [34.25, 47.51, 13.82, 48.82, 33.18, 0.1451, 0.0852, 0.0311, 0.0182, 0.1818],
    "Gemini-2.0-flash (paper)": [26.98, 56.85, 6.76, 44.41, 36.89, 0.1161, 0.0540, 0.0282, 0.0160, 0.1440],
    "Gemini-2.5-flash (paper)": [38.92, 57.13, 15.53, 48.84, 39.68, 0.1275, 0.0852, 0.0538, 0.0245, 0.1231],
    "GPT-5.4 (paper)": [45.16, 52.34, 15.88, 47.06, 38.54, 0.1194, 0.0606, 0.0307, 0.0161, 0.1520],
    "LabRobFail-VLM (paper)": [94.45, 90.83, 77.21, 83.18, 73.21, 0.7629, 0.7569, 0.7452, 0.7362, 0.7542],
}
# Paper, unseen-environment table: LabRobFail-VLM per setting (same columns).
PAPER_UNSEEN_ROWS: dict[str, list[float]] = {
    "object": [91.53, 79.15, 60.22, 53.05, 59.86, 0.4876, 0.4536, 0.3974, 0.3492, 0.4668],
    "scene": [93.42, 85.56, 74.39, 63.51, 72.63, 0.6793, 0.6276, 0.5805, 0.5229, 0.6604],
    "both": [89.09, 71.02, 41.41, 46.02, 48.72, 0.3981, 0.3875, 0.3735, 0.3269, 0.3894],
}


def paper_unseen_row(split: str) -> list[float] | None:
    """The paper's unseen row for a held-out split (val_object and test_object both sit beside "object"), or None."""
    held, _, setting = split.partition("_")
    return PAPER_UNSEEN_ROWS.get(setting) if held in ("val", "test") else None


# Paper, ablation table (seen split): Q2, Q3, Q5 accuracy %, Q6 ROUGE-L.
PAPER_ABLATION: dict[str, list[float]] = {
    "Full fine-tuning (paper)": [85.24, 72.24, 70.24, 0.7142],
    "Frozen vision (paper)": [81.13, 60.21, 61.24, 0.4529],
    "w/o temporal index (paper)": [86.45, 70.58, 69.24, 0.6471],
    "LabRobFail-VLM (paper)": [90.83, 77.21, 73.21, 0.7542],
}
HEADER = ["Method", "Q1", "Q2", "Q3", "Q4", "Q5", "BLEU-1", "BLEU-2", "BLEU-3", "BLEU-4", "ROUGE-L"]


def row(res: dict[str, Any]) -> list[float | None]:
    """All-trajectory row: Q1-Q6 over every trajectory of the split."""
    q6 = res["q6"]
    return [
        res["q1"],
        res["q2"],
        res["q3"],
        res["q4"],
        res["q5"],
        q6["bleu1"],
        q6["bleu2"],
        q6["bleu3"],
        q6["bleu4"],
        q6["rougeL"],
    ]


def paper_row(res: dict[str, Any]) -> list[float | None]:
    """Paper-comparable row: Q1 and Q2 over all trajectories, Q3-Q6 over the failed ones."""
    fo = res.get("failure_only") or {}
    q6 = fo.get("q6") or {}
    return [
        res["q1"],
        res["q2"],
        fo.get("q3"),
        fo.get("q4"),
        fo.get("q5"),
        *(q6.get(k) for k in ("bleu1", "bleu2", "bleu3", "bleu4", "rougeL")),
    ]


def detected_markdown(results: dict[str, dict[str, Any]]) -> str:
    """Failure-only Q3-Q5 and ROUGE-L over the failures each method's Q2 caught: its diagnosis apart from its
    recall (a missed failure counts wrong in the paper-comparable row)."""
    lines = [
        "### Diagnosis of the failures each method called failed",
        "",
        "| Method | failures caught | Q3 | Q4 | Q5 | ROUGE-L |",
        "|---|---|---|---|---|---|",
    ]
    f = lambda v, fmt=".2f": "—" if v is None else format(v, fmt)  # noqa: E731
    for name, res in results.items():
        d = (res.get("failure_only") or {}).get("detected") or {}
        if d.get("trajectories"):
            n_fail = res["failure_only"]["trajectories"]
            lines.append(
                f"| {name} | {d['trajectories']} of {n_fail} | {f(d['q3'])} | {f(d['q4'])} | {f(d['q5'])} | "
                f"{f((d.get('q6') or {}).get('rougeL'), '.4f')} |"
            )
    return "\n".join(lines) + "\n"


def detection_markdown(results: dict[str, dict[str, Any]], title: str) -> str:
    """Q2 as a score: AUROC, AUPRC and ECE of P(failure) per method."""
    lines = [
        f"### {title}",
        "",
        "| Method | AUROC | AUPRC | ECE | trajectories (failures) | score |",
        "|---|---|---|---|---|---|",
    ]
    for name, res in results.items():
        d = res.get("detection")
        if d:
            f = lambda v: "—" if v is None else f"{v:.4f}"  # noqa: E731
            lines.append(
                f"| {name} | {f(d['auroc'])} | {f(d['auprc'])} | {f(d['ece'])} | "
                f"{d['trajectories']} ({d['failures']}) | {d['score']} |"
            )
    return "\n".join(lines) + "\n"


def markdown(rows: dict[str, list[float | None]], title: str) -> str:
    lines = [f"### {title}", "", "| " + " | ".join(HEADER) + " |", "|" + "---|" * len(HEADER)]
    for name, vals in rows.items():
        cells = ["—" if v is None else f"{v:.2f}" if i < 5 else f"{v:.4f}" for i, v in enumerate(vals)]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def confusion_png(conf: list[list[Any]], title: str, path: Path, names: dict[str, str] | None = None) -> None:
    """`names`: tick labels for answer options (Q4: both severity vocabularies)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from labrobfail_vlm.io import save_figure

    labels = sorted({str(c[0]) for c in conf} | {str(c[1]) for c in conf})
    idx = {k: i for i, k in enumerate(labels)}
    m = np.zeros((len(labels), len(labels)), int)
    for ref, pred, n in conf:
        m[idx[str(ref)], idx[str(pred)]] += n
    fig, ax = plt.subplots(figsize=(1 + 0.6 * len(labels), 1 + 0.6 * len(labels)))
    ax.imshow(m, cmap="Blues")
    ticks = [(names or {}).get(k, k) for k in labels]
    ax.set_xticks(range(len(labels)), ticks, rotation=30 if names else 0, ha="right" if names else "center")
    ax.set_yticks(range(len(labels)), ticks)
    ax.set_xlabel("predicted")
    ax.set_ylabel("reference")
    for i in range(len(labels)):
        for j in range(len(labels)):
            ax.text(j, i, str(m[i, j]), ha="center", va="center", fontsize=8)
    ax.set_title(title)
    save_figure(fig, path, dpi=100)
