"""Two models' benches on the same splits, compared by pair: the differences a design choice is taken on. The code
behind the `labrobfail-compare` console script.

Run as:
    labrobfail-compare a=outputs/r15/rows/deep4/final b=outputs/r15/rows/aux16/final dataset_dir=outputs/r15/dataset
    labrobfail-compare a=A b=B dataset_dir=DIR splits=[train] max_trajectories=800 out=compare_train.json
    labrobfail-compare a=M b=M b_threshold=val dataset_dir=DIR   # one model at its val-chosen operating point

It reads what `labrobfail-evaluate` wrote for each model (`<model or predictions file's folder>/eval_<split>/
predictions.jsonl` at the default operating point; `a_threshold`/`b_threshold` name another one, as the bench's
`threshold=` does: eval_<split>_opval for val) and the split's gold answers, and gives, per split, these
scores of both models and the difference b - a with a 95 % interval from one seeded bootstrap over pairs: a
success/failure pair's twins share an initial state, so they are drawn together, and both models are scored on the
same draws, so the interval is that of the paired difference (narrower than two separate intervals suggest when the
models err on the same trajectories). Scores: Q2 accuracy, failure recall, false alarms (successes called failed),
AUROC of P(failure) (the hard reply where a file has no probability: the table says which), and the failure-only
(paper-comparable) Q3 / Q4 / Q5 and ROUGE-L of Q6. Choices are taken on the validation splits (the defaults); the
sealed splits are refused (they are benched for reported rows only, and their ledger lists every run).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import ListConfig

from labrobfail_vlm import questions as Q
from labrobfail_vlm.bench import evaluate as ev
from labrobfail_vlm.bench.metrics import group_draws, rouge_l_values
from labrobfail_vlm.bench.parse import parse
from labrobfail_vlm.config import ConfigError, cli_main, load_config, require_ints
from labrobfail_vlm.taxonomy import SEALED_SPLITS

# name -> (question, over which trajectories); each a mean over records, in percent (ROUGE-L as a fraction): Q2
# three ways, then the bench's failure-only scores (Q6 as its ROUGE-L)
SCORES = {"Q2": ("Q2", "all"), "recall": ("Q2", "failures"), "false_alarms": ("Q2", "successes")}
SCORES |= {("rougeL" if d == "Q6" else d): (d, "failures") for d in ev.FAILURE_ONLY_DIMS}

DEFAULTS = """\
a: null                    # the model compared against: its folder (or its predictions file), holding eval_<split>/
b: null                    # the candidate; differences are b - a
dataset_dir: null          # the dataset both were benched on (gold answers, pairs)
splits: [val, val_object, val_scene, val_both]   # validation: where choices are taken (sealed splits refused)
max_trajectories: null     # compare partial benches (eval_<split>_first<N>, e.g. splits=[train] with 800)
a_threshold: 0.5           # the operating point of a's bench, as labrobfail-evaluate's threshold= (val or a number)
b_threshold: 0.5           # the same for b: a=M b=M b_threshold=val compares a model's cut chosen on val with 0.5
resamples: 2000            # bootstrap resamples of pairs
seed: 0
out: null                  # also write the figures as JSON here
"""


def eval_dir(root: str | Path, split: str, limit: int | None, threshold: Any = 0.5) -> Path:
    """Where labrobfail-evaluate wrote `root`'s bench of `split` at operating point `threshold` (a partial run:
    eval_<split>_first<N>)."""
    return ev.bench_dir(root, split, ev.bench_suffix(threshold, limit))


def _check_args(cfg: Any) -> None:
    """Refuse a bad command line, and any missing bench, before anything is computed."""
    for key in ("a", "b", "dataset_dir"):
        if cfg[key] is None:
            raise ConfigError(f"{key}: required")
    require_ints(cfg, ("resamples",))
    require_ints(cfg, ("seed",), low=0)
    if cfg.max_trajectories is not None:
        require_ints(cfg, ("max_trajectories",))
    if not isinstance(cfg.splits, ListConfig) or not cfg.splits:
        raise ConfigError(f"splits: expected a list of split names, e.g. [val, val_both], got {cfg.splits!r}")
    if sealed := [s for s in cfg.splits if s in SEALED_SPLITS]:
        raise ConfigError(f"splits: {sealed[0]} is a sealed split (reported rows only); compare on validation")
    if cfg.out is not None and not Path(str(cfg.out)).resolve().parent.is_dir():
        raise ConfigError(f"out: no such folder {str(Path(str(cfg.out)).parent)!r}")
    for side in ("a", "b"):
        ev.check_operating_point(cfg[f"{side}_threshold"], f"{side}_threshold")
    for split in cfg.splits:
        for side in ("a", "b"):
            op = cfg[f"{side}_threshold"]
            f = eval_dir(str(cfg[side]), split, cfg.max_trajectories, op) / "predictions.jsonl"
            if not f.is_file():
                limit = f" max_trajectories={cfg.max_trajectories}" if cfg.max_trajectories else ""
                limit += f" threshold={op}" if op != 0.5 else ""
                raise ConfigError(
                    f"{side}: {f} not found (bench it first: labrobfail-evaluate model={cfg[side]} "
                    f"dataset_dir={cfg.dataset_dir} split={split}{limit})"
                )


def read_replies(
    side: str,
    root: str,
    split: str,
    limit: int | None,
    recs: list[dict],
    threshold: Any = 0.5,
    traj: dict[str, dict] | None = None,
) -> ev.Predictions:
    """`root`'s replies (at operating point `threshold`) to every record of the split, or a one-line error naming
    what is missing. With the split's trajectories (`traj`), a scored Q3 reply must weigh one option per keyframe
    the dataset's grid shows: a bench made on grids of another frame count (the same records built with another
    grid.max_frames) would have its Q3 scored against frame numbers it never saw, so it is refused."""
    f = eval_dir(root, split, limit, threshold) / "predictions.jsonl"
    preds = ev.read_predictions(f)
    if missing := sum(r["id"] not in preds for r in recs):
        raise ConfigError(f"{side}: {f} has no reply for {missing} of the split's {len(recs)} records")
    for r in recs if traj else ():
        shown = traj.get(Q.traj_of(r["id"]), {}).get("frames")
        scores = preds.option_scores.get(r["id"])
        if Q.dim_of(r["id"]) == "Q3" and scores is not None and shown is not None and len(scores) != int(shown):
            raise ConfigError(
                f"{side}: {f} weighs {len(scores)} frames in its Q3 reply to {r['id']} where the dataset's grid "
                f"shows {int(shown)}: benched on grids of another frame count, not this dataset's"
            )
    return preds


def trajectory_info(recs: list[dict], traj: dict[str, dict]) -> dict[str, tuple[bool, str]]:
    """(failed, pair) of every trajectory the split's records ask about; a missing one is a one-line error."""
    out = {}
    for t in dict.fromkeys(Q.traj_of(r["id"]) for r in recs):
        if t not in traj or "success" not in traj[t]:
            raise ConfigError(f"dataset_dir: trajectory {t} is asked about but not in trajectories.json")
        out[t] = (not traj[t]["success"], str(traj[t].get("group") or t))  # no pair known: the trajectory alone
    return out


def select(recs: list[dict], info: dict[str, tuple[bool, str]], dim: str, who: str) -> list[dict]:
    """The records of question `dim` over all trajectories, the failures or the successes."""
    return [
        r
        for r in recs
        if Q.dim_of(r["id"]) == dim and (who == "all" or info[Q.traj_of(r["id"])][0] == (who == "failures"))
    ]


def values(rs: list[dict], preds: ev.Predictions, dim: str, who: str) -> np.ndarray:
    """One value per record: ROUGE-L for Q6; for the successes' Q2, 1 where the reply says failed (its mean is the
    false-alarm rate, an unreadable reply not counted as an alarm); otherwise 1 for the right answer."""
    refs = [r["conversations"][1]["value"] for r in rs]
    if dim == "Q6":
        return np.array(rouge_l_values(refs, [parse(dim, preds[r["id"]]) or "" for r in rs]))
    if who == "successes":
        return np.array([ev.says_failed(r, preds) for r in rs], float)
    return np.array([parse(dim, preds[r["id"]]) == ref for r, ref in zip(rs, refs)], float)


def row(a: float, b: float, diffs: np.ndarray, scale: float, digits: int) -> dict[str, Any]:
    """Both figures, b - a and its interval (None when no resample could be scored), scaled and rounded."""

    def r(x: float) -> float:
        return round(scale * float(x), digits)

    ci = [r(np.percentile(diffs, q)) for q in (2.5, 97.5)] if diffs.size else None
    return {"a": r(a), "b": r(b), "diff": r(b - a), "ci95": ci}


def compare_split(
    recs: list[dict], traj: dict[str, dict], a: ev.Predictions, b: ev.Predictions, resamples: int, seed: int
) -> dict[str, Any]:
    """Every score of both models on one split with the paired 95 % interval of b - a."""
    info = trajectory_info(recs, traj)
    col = {g: i for i, g in enumerate(sorted({pair for _, pair in info.values()}))}
    drawn = group_draws(len(col), resamples, seed)  # one draw for every score: the differences are paired

    def weights(rs: list[dict]) -> np.ndarray:  # how often each record is drawn, per resample
        return drawn[:, [col[info[Q.traj_of(r["id"])][1]] for r in rs]]

    out: dict[str, Any] = {"trajectories": len(info), "pairs": len(col)}
    for name, (dim, who) in SCORES.items():
        if not (rs := select(recs, info, dim, who)):
            continue
        w = weights(rs)
        va, vb = values(rs, a, dim, who), values(rs, b, dim, who)
        n = w.sum(1)
        diffs = (w[n > 0] @ (vb - va)) / n[n > 0]
        out[name] = row(va.mean(), vb.mean(), diffs, *((1, 4) if dim == "Q6" else (100, 2)))
    q2 = select(recs, info, "Q2", "all")
    y = np.array([info[Q.traj_of(r["id"])][0] for r in q2], bool)
    if 0 < y.sum() < len(y):
        (sa, ka), (sb, kb) = ev.failure_scores(q2, a), ev.failure_scores(q2, b)
        out["auroc"] = {**auroc_row(y, np.array(sa), np.array(sb), weights(q2)), "score": {"a": ka, "b": kb}}
    return out


def auroc_row(y: np.ndarray, sa: np.ndarray, sb: np.ndarray, w: np.ndarray) -> dict[str, Any]:
    """AUROC of each score and the paired interval of the difference. A record drawn k times weighs k, which gives
    the AUROC of the resample itself; resamples holding one class only are skipped."""
    from sklearn.metrics import roc_auc_score

    keep = [wt for wt in w if 0 < wt[y].sum() < wt.sum()]
    diffs = np.array([roc_auc_score(y, sb, sample_weight=wt) - roc_auc_score(y, sa, sample_weight=wt) for wt in keep])
    return row(roc_auc_score(y, sa), roc_auc_score(y, sb), diffs, 1, 4)


def bench_cut(folder: Path) -> float | None:
    """The P(failure) cut a bench ran at (its results.json's `threshold`), or None where it does not say."""
    try:
        return float(json.loads((folder / "results.json").read_text())["threshold"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def op_text(threshold: Any, cut: float | None) -> str:
    """The markdown header's words for a side's operating point (none for the default 0.5)."""
    if threshold == 0.5:
        return ""
    return f" (operating point {threshold}" + ("" if cut is None else f": P(failure) >= {cut:.3f}") + ")"


def markdown(res: dict[str, Any]) -> str:
    """The comparison as one Markdown table, a line per split and score."""
    at = {k: op_text(res[f"{k}_threshold"], res.get(f"{k}_cut")) for k in "ab"}
    lines = [
        f"a = {res['a']}{at['a']}  \nb = {res['b']}{at['b']}  \n95 % intervals: {res['ci_method']}",
        "",
        "| split | score | a | b | b - a [95 % CI] |",
        "|---|---|---|---|---|",
    ]
    for split, rows in res["splits"].items():
        for name in (*SCORES, "auroc"):
            if (r := rows.get(name)) is None:
                continue
            ci = "[{:+}, {:+}]".format(*r["ci95"]) if r["ci95"] else "(no resample)"
            kind = " (hard reply)" if name == "auroc" and "hard" in r["score"].values() else ""
            lines.append(f"| {split} | {name}{kind} | {r['a']} | {r['b']} | {r['diff']:+} {ci} |")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    from labrobfail_vlm.io import atomic_write_json

    cfg = load_config(DEFAULTS, argv)
    _check_args(cfg)
    res: dict[str, Any] = {
        "a": str(cfg.a),
        "b": str(cfg.b),
        "a_threshold": cfg.a_threshold,
        "b_threshold": cfg.b_threshold,
        "dataset_dir": str(cfg.dataset_dir),
        "ci_method": f"percentile bootstrap over pairs (both models on the same draws), {cfg.resamples} resamples, "
        f"seed {cfg.seed}",
        "splits": {},
    }
    for k in "ab":  # the cut a val-chosen bench ran at (its results.json says; chosen once, the same on every split)
        if cfg[f"{k}_threshold"] == "val":
            res[f"{k}_cut"] = bench_cut(eval_dir(str(cfg[k]), cfg.splits[0], cfg.max_trajectories, "val"))
    for split in cfg.splits:
        recs, traj = ev.load_split(cfg.dataset_dir, split, cfg.max_trajectories)
        if not recs:
            raise ConfigError(f"splits: {split} has no records in {cfg.dataset_dir}")
        a, b = (
            read_replies(k, str(cfg[k]), split, cfg.max_trajectories, recs, cfg[f"{k}_threshold"], traj) for k in "ab"
        )
        res["splits"][split] = compare_split(recs, traj, a, b, cfg.resamples, cfg.seed)
    print(markdown(res))
    if cfg.out is not None:
        atomic_write_json(Path(str(cfg.out)), res)
    return 0


def cli() -> None:
    """The `labrobfail-compare` console script."""
    cli_main(main, __doc__)
