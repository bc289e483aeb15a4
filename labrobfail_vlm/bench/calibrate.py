"""Option biases for the closed failure-only questions (Q3 frame, Q4 severity, Q5 category), fitted on a model's
own seen-val bench: the code behind the `labrobfail-calibrate` console script (labrobfail_vlm/option_bias.py says
what a bias does and why).

Run as:
    labrobfail-evaluate model=M dataset_dir=D split=val            # the bench it fits on (its predictions' scores)
    labrobfail-calibrate model=M dataset_dir=D out=M_cal           # M's files, labrobfail.json with option_bias
    labrobfail-calibrate model=M dataset_dir=D out=M_cal objective=accuracy dims=[Q4]
    labrobfail-calibrate model=M dataset_dir=D out=M_q dims=[] failure_score=questions   # no bias: Q2 from Q2-Q5

Fits on the seen-val failures whose Q2 the model called a failure (the only rows it answers Q3-Q5 on; their
options' log-likelihoods are in M/eval_val/predictions.jsonl), one dimension at a time, and writes `out`: a new
folder with M's model files (not its benches) and the biases in labrobfail.json. It prints, per dimension, the
failure-only score on seen val (the split fitted on: optimistic) and on each `check` split (held-out validation
splits M was already benched on) before and after, from M's own predictions with the biases applied (no model run;
the scores are stored to 5 decimals, so a near-tie may fall the other way in a real run). Whether to take the
calibrated model is then decided on validation like any choice (labrobfail-compare on benches of `out`).
`failure_score=` also writes how the copy reads P(failure) (labrobfail_vlm.failure_score): nothing is
fitted for it, and its effect is seen only by benching `out`.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

from omegaconf import ListConfig

from labrobfail_vlm import questions as Q
from labrobfail_vlm.bench import evaluate as ev
from labrobfail_vlm.bench.compare import read_replies
from labrobfail_vlm.config import ConfigError, cli_main, load_config
from labrobfail_vlm.option_bias import BIASED_DIMS, OBJECTIVES, biased_choice, fit_bias, option_count
from labrobfail_vlm.taxonomy import SEALED_SPLITS

DEFAULTS = """\
model: null                 # a fine-tuned checkpoint folder (labrobfail.json) benched on seen val (eval_val/)
dataset_dir: null           # the dataset it was benched on (gold answers)
out: null                   # the calibrated checkpoint's folder: new (an existing one is refused)
dims: [Q3, Q4, Q5]          # the closed failure-only questions to bias
objective: likelihood       # likelihood (the prior correction: convex, smooth) | accuracy (coordinate ascent)
ridge: 0.01                 # likelihood: keeps an option no val failure has finite
check: [val_object, val_scene, val_both]   # held-out validation benches of model= re-scored with the biases
failure_score: null         # q2 | questions | wordings: written into the copy (null: the model's own); dims=[]: no bias
"""


def with_bias(preds: ev.Predictions, bias: dict[str, list[float]]) -> ev.Predictions:
    """`preds` with each scored closed reply of a biased dimension chosen again with its bias (options "1".."n")."""
    out = ev.Predictions(preds, p_failure=preds.p_failure, option_scores=preds.option_scores)
    for rid, sc in preds.option_scores.items():
        if (d := Q.dim_of(rid)) in bias:
            out[rid] = str(biased_choice(sc, bias[d]) + 1)
    return out


def fit_rows(recs: list[dict], preds: ev.Predictions, dim: str) -> tuple[list[list[float]], list[int]]:
    """(option scores, gold option 0-based) of `dim`'s records that are failures with a scored reply."""
    scores, gold = [], []
    for r in recs:
        ref = r["conversations"][1]["value"]
        if Q.dim_of(r["id"]) == dim and ref.isdigit() and r["id"] in preds.option_scores:
            scores.append(preds.option_scores[r["id"]])
            gold.append(int(ref) - 1)
    return scores, gold


def _check_args(cfg: Any) -> None:
    for k in ("model", "dataset_dir", "out"):
        if cfg[k] is None:
            raise ConfigError(f"{k}: required (labrobfail-calibrate model=DIR dataset_dir=DIR out=DIR)")
    if not (Path(cfg.model) / "labrobfail.json").is_file():
        raise ConfigError(f"model: {cfg.model} is not a fine-tuned checkpoint (no labrobfail.json)")
    out, model = Path(cfg.out).resolve(), Path(cfg.model).resolve()
    if out.exists() or out.with_name(out.name + ".tmp").exists():
        raise ConfigError(f"out: {cfg.out} (or its .tmp) exists (a calibrated checkpoint is written to a new folder)")
    if out.is_relative_to(model):
        raise ConfigError(f"out: {cfg.out} is inside model= (the copy would hold copies)")
    if cfg.objective not in OBJECTIVES:
        raise ConfigError(f"objective: expected one of {', '.join(OBJECTIVES)}, got {cfg.objective!r}")
    if cfg.failure_score is not None:
        from labrobfail_vlm.failure_score import check_failure_score

        try:
            check_failure_score(cfg.failure_score)
        except ValueError as e:
            raise ConfigError(str(e)) from None
    dims = cfg.dims
    if (
        not isinstance(dims, ListConfig)
        or (not dims and cfg.failure_score is None)
        or any(d not in BIASED_DIMS for d in dims)
    ):
        raise ConfigError(
            f"dims: expected a list of {', '.join(BIASED_DIMS)} (or [] with failure_score=), got {cfg.dims!r}"
        )
    if cfg.check is None or isinstance(cfg.check, str) or not all(isinstance(s, str) for s in cfg.check):
        raise ConfigError(f"check: expected a list of validation splits (or []), got {cfg.check!r}")
    if any(s in SEALED_SPLITS or s.startswith("test") for s in cfg.check):
        raise ConfigError("check: validation splits only (choices are taken on validation)")
    r = cfg.ridge
    if isinstance(r, bool) or not isinstance(r, (int, float)) or not 0 <= r < float("inf"):
        raise ConfigError(f"ridge: expected a number >= 0, got {r!r}")


def _bench(
    model: str, dataset_dir: str, split: str, dims: list[str]
) -> tuple[list[dict], dict[str, dict], ev.Predictions]:
    """A bench of `model` on `split` whose predictions carry option scores for each of `dims` (a bench written
    before the scores were kept would re-score as unchanged: refused)."""
    recs, traj = ev.load_split(dataset_dir, split)
    preds = read_replies("model", model, split, None, recs)  # every record answered, as compare asks
    f = ev.bench_dir(model, split) / "predictions.jsonl"
    have = {Q.dim_of(i) for i in preds.option_scores}
    if missing := [d for d in dims if d not in have]:
        raise ConfigError(f"{f} has no option scores for {', '.join(missing)} (bench it again with this version)")
    return recs, traj, preds


def write_checkpoint(
    model: str | Path, out: str | Path, bias: dict[str, list[float]], fit: dict[str, Any], score: str | None = None
) -> None:
    """`model`'s files (benches, checkpoints and logs left out; linked files copied) in a new folder `out`, its
    labrobfail.json with `bias` over any biases it had (a dimension not refitted keeps its own), `fit`, and the
    failure score `score` if given; written beside as <out>.tmp and renamed, so a stopped run leaves no half
    folder under `out`'s name."""
    src, dst = Path(model), Path(out)
    tmp = dst.with_name(dst.name + ".tmp")
    skip = shutil.ignore_patterns("eval_*", "checkpoint-*", "wandb", "*.log")
    try:
        shutil.copytree(src, tmp, ignore=skip, symlinks=False)
        man = json.loads((tmp / "labrobfail.json").read_text())
        if bias:  # dims=[] with a failure score: the biases the model had, if any, stay as they were
            man["option_bias"] = {**(man.get("option_bias") or {}), **bias}
            man["option_bias_fit"] = fit
        if score is not None:
            man["failure_score"] = score
        (tmp / "labrobfail.json").write_text(json.dumps(man, indent=1))
        tmp.rename(dst)
    except (OSError, ValueError) as e:
        shutil.rmtree(tmp, ignore_errors=True)
        raise ConfigError(f"out: cannot write {dst} ({type(e).__name__}: {e})") from None


def main(argv: list[str]) -> int:
    cfg = load_config(DEFAULTS, argv)
    _check_args(cfg)
    dims = list(cfg.dims)
    if not dims:  # a failure score alone: nothing is fitted, no bench is read
        write_checkpoint(str(cfg.model), str(cfg.out), {}, {}, cfg.failure_score)
        print(f"wrote {cfg.out} (failure_score {cfg.failure_score})")
        return 0
    recs, traj, preds = _bench(str(cfg.model), str(cfg.dataset_dir), "val", dims)
    bias: dict[str, list[float]] = {}
    report = []
    for d in dims:
        scores, gold = fit_rows(recs, preds, d)
        if not scores:
            raise ConfigError(f"{cfg.model}/eval_val: no failure it found has a gold {d} option to fit on")
        try:
            # Q3's options are the keyframes shown: as many as the longest scored reply offers
            n = option_count(d, max(len(s) for s in scores))
            bias[d] = fit_bias(scores, gold, n, cfg.objective, float(cfg.ridge))
        except (ValueError, ImportError) as e:  # a fit that did not converge; scipy missing (the bench extra)
            raise ConfigError(f"{d}: {e}") from None
        report.append(f"{d}: fitted on {len(gold)} seen-val failures, biases {bias[d]}")
    checks = {"val": (recs, traj, preds)}
    checks |= {s: _bench(str(cfg.model), str(cfg.dataset_dir), s, dims) for s in cfg.check}
    report.append("| split | dim | failure-only before | after |\n|---|---|---|---|")
    for split, (r, t, p) in checks.items():
        before, after = ev.score(r, p, t)["failure_only"], ev.score(r, with_bias(p, bias), t)["failure_only"]
        for d in dims:
            tag = " (fitted on)" if split == "val" else ""
            report.append(f"| {split}{tag} | {d} | {before[d.lower()]} | {after[d.lower()]} |")
    fit = {"on": f"{cfg.dataset_dir} val", "objective": cfg.objective, "dims": dims}
    write_checkpoint(str(cfg.model), str(cfg.out), bias, fit, cfg.failure_score)
    print("\n".join(report))
    print(f"wrote {cfg.out}")
    return 0


def cli() -> None:
    """The `labrobfail-calibrate` console script."""
    cli_main(main, __doc__)
