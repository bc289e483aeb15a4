"""Two models' benches on the same splits, compared by pair: the differences a design choice is taken on. The code
behind the `labrobfail-compare` console script.

Run as:
    labrobfail-compare a=outputs/r15/rows/deep4/final b=outputs/r15/rows/aux16/final dataset_dir=outputs/r15/dataset
    labrobfail-compare a=A b=B dataset_dir=DIR splits=[train] max_trajectories=800 out=compare_train.json

It reads what `labrobfail-evaluate` wrote for each model (`<dir>/eval_<split>/predictions.jsonl`) and the split's
gold answers, and gives, per split, each score of both models and the difference b - a with a 95 % interval from
one seeded bootstrap over pairs: a success/failure pair's twins share an initial state, so they are drawn together,
and both models are scored on the same draw, so the interval is that of the paired difference (narrower than two
separate intervals suggest when the models err on the same trajectories). Scores: Q2 accuracy, failure recall,
false alarms (successes not answered as successes), AUROC of P(failure) (the hard reply where a file has no
probability), and the failure-only (paper-comparable) Q3 / Q4 / Q5 and ROUGE-L of Q6. Choices are taken on the
validation splits (the defaults); a test split here compares rows already reported, it runs nothing.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from labrobfail_vlm import questions as Q
from labrobfail_vlm.bench import evaluate as ev
from labrobfail_vlm.bench.metrics import group_draws, rouge_l_values
from labrobfail_vlm.bench.parse import parse
from labrobfail_vlm.config import ConfigError, cli_main, load_config, require_ints

# name -> (question, over which trajectories); each a mean over records, in percent (ROUGE-L as a fraction)
SCORES = {
    "Q2": ("Q2", "all"),
    "recall": ("Q2", "failures"),
    "false_alarms": ("Q2", "successes"),
    "Q3": ("Q3", "failures"),
    "Q4": ("Q4", "failures"),
    "Q5": ("Q5", "failures"),
    "rougeL": ("Q6", "failures"),
}

DEFAULTS = """\
a: null                    # the model (or predictions folder) compared against: the one holding eval_<split>/
b: null                    # the candidate; differences are b - a
dataset_dir: null          # the dataset both were benched on (gold answers, pairs)
splits: [val, val_object, val_scene, val_both]   # validation: where choices are taken
max_trajectories: null     # compare partial benches (eval_<split>_first<N>, e.g. splits=[train] with 800)
resamples: 2000            # bootstrap resamples of pairs
seed: 0
out: null                  # also write the figures as JSON here
"""


def eval_dir(root: str | Path, split: str, limit: int | None) -> Path:
    """Where labrobfail-evaluate wrote `root`'s bench of `split` (a partial run: eval_<split>_first<N>)."""
    return Path(root) / (f"eval_{split}_first{limit}" if limit else f"eval_{split}")


def read_replies(side: str, root: str | Path, split: str, limit: int | None, recs: list[dict]) -> ev.Predictions:
    """`root`'s replies to every record of the split, or a one-line error naming what is missing."""
    f = eval_dir(root, split, limit) / "predictions.jsonl"
    if not f.is_file():
        raise ConfigError(f"{side}: {f} not found (bench it first: labrobfail-evaluate model={root} split={split})")
    preds = ev.read_predictions(f)
    if missing := sum(r["id"] not in preds for r in recs):
        raise ConfigError(f"{side}: {f} has no reply for {missing} of the split's {len(recs)} records")
    return preds


def select(recs: list[dict], traj: dict[str, dict], dim: str, who: str) -> list[dict]:
    """The records of question `dim` over all trajectories, the failures or the successes."""
    return [
        r
        for r in recs
        if Q.dim_of(r["id"]) == dim and (who == "all" or traj[Q.traj_of(r["id"])]["success"] == (who == "successes"))
    ]


def values(rs: list[dict], preds: dict[str, str], dim: str, who: str) -> np.ndarray:
    """One value per record: ROUGE-L for Q6; otherwise 1 for a right answer (for successes: 1 for a wrong one,
    which makes the mean the false-alarm rate)."""
    refs = [r["conversations"][1]["value"] for r in rs]
    replies = [parse(dim, preds[r["id"]]) for r in rs]
    if dim == "Q6":
        return np.array(rouge_l_values(refs, [p or "" for p in replies]))
    return np.array([(p == ref) != (who == "successes") for p, ref in zip(replies, refs)], float)


def p_failure(q2: list[dict], preds: ev.Predictions) -> np.ndarray:
    """P(failure) per Q2 record; the hard reply (1 or 0) where the file gives no probability."""
    return np.array([preds.p_failure.get(Q.traj_of(r["id"]), float(ev.says_failed(r, preds))) for r in q2])


def _row(a: float, b: float, diffs: np.ndarray, scale: float, digits: int) -> dict[str, Any]:
    r = lambda x: round(scale * float(x), digits)  # noqa: E731
    return {"a": r(a), "b": r(b), "diff": r(b - a), "ci95": [r(np.percentile(diffs, q)) for q in (2.5, 97.5)]}


def compare_split(
    recs: list[dict], traj: dict[str, dict], a: ev.Predictions, b: ev.Predictions, resamples: int, seed: int
) -> dict[str, Any]:
    """Every score of both models on one split with the paired 95 % interval of b - a."""
    group_of = lambda r: str(traj[Q.traj_of(r["id"])].get("group") or Q.traj_of(r["id"]))  # noqa: E731
    col = {g: i for i, g in enumerate(sorted({group_of(r) for r in recs}))}
    drawn = group_draws(len(col), resamples, seed)  # one draw for every score: the differences are paired
    out: dict[str, Any] = {"trajectories": len(select(recs, traj, "Q2", "all")), "pairs": len(col)}
    for name, (dim, who) in SCORES.items():
        if not (rs := select(recs, traj, dim, who)):
            continue
        w = drawn[:, [col[group_of(r)] for r in rs]]  # how often each record is drawn, per resample
        va, vb = values(rs, a, dim, who), values(rs, b, dim, who)
        n = w.sum(1)
        diffs = (w[n > 0] @ (vb - va)) / n[n > 0]
        out[name] = _row(va.mean(), vb.mean(), diffs, *((1, 4) if dim == "Q6" else (100, 2)))
    q2 = select(recs, traj, "Q2", "all")
    y = np.array([not traj[Q.traj_of(r["id"])]["success"] for r in q2])
    if 0 < y.sum() < len(y):
        out["auroc"] = _auroc(y, p_failure(q2, a), p_failure(q2, b), drawn[:, [col[group_of(r)] for r in q2]])
    return out


def _auroc(y: np.ndarray, sa: np.ndarray, sb: np.ndarray, w: np.ndarray) -> dict[str, Any]:
    """AUROC of each score and the paired interval of the difference: a record drawn k times weighs k (which is
    the AUROC of the resample itself); resamples holding one class only are skipped."""
    from sklearn.metrics import roc_auc_score

    keep = [wt for wt in w if 0 < wt[y].sum() < wt.sum()]
    diffs = np.array([roc_auc_score(y, sb, sample_weight=wt) - roc_auc_score(y, sa, sample_weight=wt) for wt in keep])
    return _row(roc_auc_score(y, sa), roc_auc_score(y, sb), diffs, 1, 4)


def markdown(res: dict[str, Any]) -> str:
    lines = [
        f"a = {res['a']}  \nb = {res['b']}  \n95 % intervals: {res['ci_method']}",
        "",
        "| split | score | a | b | b - a [95 % CI] |",
        "|---|---|---|---|---|",
    ]
    for split, rows in res["splits"].items():
        for name in (*SCORES, "auroc"):
            if (r := rows.get(name)) is not None:
                lo, hi = r["ci95"]
                lines.append(f"| {split} | {name} | {r['a']} | {r['b']} | {r['diff']:+} [{lo:+}, {hi:+}] |")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    from labrobfail_vlm.io import atomic_write_json

    cfg = load_config(DEFAULTS, argv)
    for key in ("a", "b", "dataset_dir"):
        if cfg[key] is None:
            raise ConfigError(f"{key}: required")
    require_ints(cfg, ("resamples",))
    if cfg.max_trajectories is not None:
        require_ints(cfg, ("max_trajectories",))
    res: dict[str, Any] = {
        "a": str(cfg.a),
        "b": str(cfg.b),
        "dataset_dir": str(cfg.dataset_dir),
        "ci_method": f"percentile bootstrap over pairs (both models on the same draws), {cfg.resamples} resamples, "
        f"seed {cfg.seed}",
        "splits": {},
    }
    for split in cfg.splits:
        recs, traj = ev.load_split(cfg.dataset_dir, split, cfg.max_trajectories)
        a, b = (read_replies(k, cfg[k], split, cfg.max_trajectories, recs) for k in ("a", "b"))
        res["splits"][split] = compare_split(recs, traj, a, b, cfg.resamples, cfg.seed)
    if cfg.out is not None:
        atomic_write_json(Path(cfg.out), res)
    print(markdown(res))
    return 0


def cli() -> None:
    """The `labrobfail-compare` console script."""
    cli_main(main, __doc__)
