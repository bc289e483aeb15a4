"""Score a model (or a predictions file) on LabRobFail-Bench and write results.json, results.md and PNGs. The code
behind the `labrobfail-evaluate` console script.

Run as:
    labrobfail-evaluate model=outputs/demo_train/final dataset_dir=outputs/demo_dataset split=test
    labrobfail-evaluate predictions=preds.jsonl dataset_dir=outputs/dataset split=val_object
    labrobfail-evaluate model=DIR dataset_dir=DIR external.enabled=true external.model=gpt-4o
    labrobfail-evaluate endpoint=http://127.0.0.1:8000/v1 dataset_dir=outputs/dataset split=test
    labrobfail-evaluate model=DIR dataset_dir=DIR batch_size=16      # grids decoded together
    labrobfail-evaluate model=DIR dataset_dir=DIR split=val_both threshold=val   # Q2's operating point chosen on val
    labrobfail-evaluate model=DIR dataset_dir=DIR split=train max_trajectories=800   # how well it fits its own data
    labrobfail-evaluate model=DIR dataset_dir=DIR executable.enabled=true executable.shards=SHARDS_DIR

results.json: q1..q5 (top-1 %, Q1 exact ordered list, Q3 exact frame), q3_within1, q6 {bleu1..bleu4
(nltk corpus_bleu, smoothing method1), rougeL (rouge-score, stemmer)} over ALL trajectories, breakdowns per
category and task, confusion matrices; `failure_only`: Q3-Q6 over the failed trajectories (the paper-comparable
scores); `detection`: AUROC, AUPRC and ECE of P(failure) (reliability_q2.png); plus the same for each baseline.
With `executable.enabled`, `q6_executable`: the share of failures that the model's (and the gold) corrections fix
when run in the simulator (sim_backends/supervision/executable.py; needs the simulator installed, and it is the
one place the model core reaches into it, by name and only when asked). Defaults: configs/evaluate.yaml.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from labrobfail_vlm.config import ConfigError, cli_main, load_config
from labrobfail_vlm.taxonomy import SEALED_SPLITS


def _check_args(cfg: Any) -> None:
    """Refuse a bad command line before anything is read or written."""
    if cfg.mode not in ("offline", "online"):
        raise ConfigError(f"mode: expected offline or online, got {cfg.mode!r}")
    given = sum(x is not None for x in (cfg.model, cfg.predictions, cfg.endpoint))
    if given != 1 and not (given == 0 and cfg.mode == "online"):  # online without one: the robot's monitors alone
        raise ConfigError("model/predictions/endpoint: give exactly one of model=DIR, predictions=FILE or endpoint=URL")
    if cfg.dataset_dir is None:
        raise ConfigError("dataset_dir: required")
    if not isinstance(cfg.split, str):
        raise ConfigError(f"split: expected one split's name (split=test), got {cfg.split!r}")
    if cfg.scored_dataset is not None and cfg.mode != "online":
        raise ConfigError("scored_dataset: mode=online only (the alarm fitted on dataset_dir, another dataset scored)")
    if cfg.executable.enabled and not cfg.executable.shards:  # before the model runs, not after
        raise ConfigError("executable.shards: name the shard folder(s) the dataset was built from")
    if cfg.max_trajectories is not None and (not isinstance(cfg.max_trajectories, int) or cfg.max_trajectories < 1):
        raise ConfigError(f"max_trajectories: expected a positive integer or null, got {cfg.max_trajectories!r}")
    if cfg.max_trajectories is not None and cfg.mode == "offline" and cfg.split in SEALED_SPLITS:
        # a sealed split runs whole, for a reported row, and its ledger line carries whole-split figures
        raise ConfigError(f"max_trajectories: {cfg.split} is a sealed split; it is benched whole or not at all")
    if not isinstance(cfg.batch_size, int) or cfg.batch_size < 1:
        raise ConfigError(f"batch_size: expected a positive integer, got {cfg.batch_size!r}")
    from labrobfail_vlm.train.tower_cache import check_cache_mb

    check_cache_mb(cfg.tower_cache_mb, auto=True)
    if isinstance(cfg.baselines, str) or any(b not in ("majority", "blind") for b in cfg.baselines or []):
        raise ConfigError(f"baselines: a list of majority and blind ('baselines=[majority]'), got {cfg.baselines!r}")
    if cfg.threshold != 0.5:
        from labrobfail_vlm.bench.evaluate import check_operating_point

        check_operating_point(cfg.threshold)
        if cfg.model is None or cfg.mode == "online":  # an endpoint's or a file's replies are what they are
            raise ConfigError("threshold: only a local model's run (model=, offline mode) has an operating point")
    if cfg.model is not None and not Path(cfg.model).is_dir():  # before anything is written
        raise ConfigError(f"model: no such directory {cfg.model!r}")
    if cfg.predictions is not None:  # a folder or an unreadable file is refused before the output folder is made
        try:
            with open(str(cfg.predictions), "rb") as f:  # str(): open(5) would read file descriptor 5
                f.read(1)
        except OSError as e:
            raise ConfigError(
                f"predictions: cannot read {cfg.predictions} ({e.strerror or type(e).__name__})"
            ) from None


def val_threshold(model: str | Path, dataset_dir: str | Path) -> float:
    """The operating point with the best Q2 accuracy on the model's own seen-val bench (its predictions.jsonl)."""
    from labrobfail_vlm.bench import evaluate as ev
    from labrobfail_vlm.bench.detection import accuracy_threshold

    f = ev.bench_dir(model, "val") / "predictions.jsonl"
    if not f.is_file():
        raise ConfigError(f"threshold=val: {f} not found (run labrobfail-evaluate split=val with threshold=0.5 first)")
    p = ev.read_predictions(f).p_failure
    _, traj = ev.load_split(dataset_dir, "val")
    ids = [t for t in traj if t in p]
    if not ids:
        raise ConfigError(f"threshold=val: {f} scores no trajectory of {dataset_dir}'s val split")
    return accuracy_threshold([not traj[t].get("success", True) for t in ids], [p[t] for t in ids])


def _out_dir(cfg: Any) -> Path:
    """The output folder (made): out_dir, or eval_<split> beside the model or predictions file (eval_<split>_opval
    at the operating point chosen on val, eval_<split>_t<threshold> at another given one; _first<N> added for a run
    on the split's first N trajectories)."""
    from labrobfail_vlm.bench.evaluate import bench_dir, bench_suffix

    op = bench_suffix(cfg.threshold, cfg.max_trajectories)
    if cfg.endpoint is not None:
        out = Path(cfg.out_dir or Path("outputs") / f"eval_endpoint_{cfg.split}{op}")
    else:
        out = Path(cfg.out_dir or bench_dir(cfg.model or cfg.predictions, cfg.split, op))
    out.mkdir(parents=True, exist_ok=True)
    return out


def _load_analyzer(cfg: Any, threshold: float = 0.5, cache: bool = True) -> tuple[Any, str]:
    """The endpoint or local model (at the Q2 operating point `threshold`) that answers, and its row name. `cache`: a
    local model's tower outputs are kept for the bench's later passes over the same grids (tower_cache_mb)."""
    if cfg.endpoint is not None:
        from labrobfail_vlm.endpoint import EndpointAnalyzer

        analyzer = EndpointAnalyzer(
            str(cfg.endpoint),
            cfg.endpoint_model,
            cfg.endpoint_key_env,
            cfg.endpoint_timeout_s,
            concurrency=cfg.batch_size,
        )
        return analyzer, f"LabRobFail-VLM endpoint ({analyzer.client.model})"
    from labrobfail_vlm.analyzer import FailureAnalyzer
    from labrobfail_vlm.train.tower_cache import inference_cache

    analyzer = FailureAnalyzer.from_pretrained(cfg.model, threshold=threshold)
    if cache:
        mb = cfg.tower_cache_mb
        if mb == "auto":  # on CPU the tower is most of a pass; on a GPU it is cheap and the memory is the model's
            mb = 1024 if next(analyzer.model.parameters()).device.type == "cpu" else 0
        inference_cache(analyzer.model, float(mb))
    return analyzer, "LabRobFail-VLM (" + Path(cfg.model).name + ")"


def _predict(
    cfg: Any, recs: list[dict], traj: dict[str, dict], results: dict[str, dict], threshold: float = 0.5
) -> tuple[Any, str, Any, dict[str, str]]:
    """Run the model (at the Q2 operating point `threshold`) or endpoint, or read the predictions file: (analyzer or
    None, row name, predictions, Q6 template predictions). A template run's scores go into `results` under
    "<name>, Q6 template"."""
    from labrobfail_vlm.bench import evaluate as ev

    tmpl: dict[str, str] = {}  # Q6 in template mode (model and endpoint runs)
    if cfg.model is None and cfg.endpoint is None:
        preds = ev.read_predictions(cfg.predictions)
        if not any(r["id"] in preds for r in recs):  # else every reply scores as missing, silently 0.00
            raise ConfigError(
                f"predictions: no id of {cfg.predictions} is a record of split {cfg.split} (empty, or another split's)"
            )
        return None, Path(cfg.predictions).stem, preds, tmpl
    analyzer, name = _load_analyzer(cfg, threshold)
    preds = ev.model_predictions(
        analyzer, cfg.dataset_dir, recs, traj, progress=cfg.progress, batch_size=cfg.batch_size
    )
    q6 = [r for r in recs if r["id"].endswith("_Q6")]
    if cfg.q6_template and q6:
        # the same model, Q6 chosen among the correction-strategy table's filled templates; the other
        # answers do not depend on the Q6 mode, so only Q6 (and the Q2 verdict it follows) is asked again
        analyzer.q6_mode = "template"
        tmpl = ev.model_predictions(
            analyzer, cfg.dataset_dir, q6, traj, progress=cfg.progress, batch_size=cfg.batch_size
        )
        results[name + ", Q6 template"] = ev.score(
            recs, ev.Predictions({**preds, **tmpl}, p_failure=preds.p_failure), traj
        )
        analyzer.q6_mode = "free"
    return analyzer, name, preds, tmpl


def _write_predictions(out: Path, preds: Any) -> None:
    """predictions.jsonl: every answer, with P(failure) on each Q2 line whose trajectory has one and the options'
    log-likelihoods on each closed failure-only reply the model chose."""
    from labrobfail_vlm import questions as Q
    from labrobfail_vlm.io import atomic_write_bytes

    p_fail = getattr(preds, "p_failure", {})
    scores = getattr(preds, "option_scores", {})
    atomic_write_bytes(
        out / "predictions.jsonl",
        "".join(
            json.dumps(
                {
                    "id": k,
                    "prediction": v,
                    **(
                        {"p_failure": round(p_fail[Q.traj_of(k)], 6)}
                        if k.endswith("_Q2") and Q.traj_of(k) in p_fail
                        else {}
                    ),
                    **({"scores": scores[k]} if k in scores else {}),
                }
            )
            + "\n"
            for k, v in preds.items()
        ).encode(),
    )


def _score_baselines(
    cfg: Any, recs: list[dict], traj: dict[str, dict], analyzer: Any, results: dict[str, dict], log_lines: list[str]
) -> None:
    """Score the configured baselines (majority, blind) into `results`."""
    from labrobfail_vlm.bench import evaluate as ev

    for b in cfg.baselines or []:  # checked by _check_args: majority and blind only
        if b == "majority":  # needs training answers: this dataset's train split, or majority_train=DIR's
            train_dir = cfg.majority_train or cfg.dataset_dir
            try:
                train, train_traj = ev.load_split(train_dir, "train")
                train = ev.same_kind(train, train_traj, recs, traj)
                results[ev.MAJORITY] = ev.score(
                    recs,
                    ev.majority_predictions(train, recs),
                    traj,
                    failure_preds=ev.majority_predictions(train, recs, True),
                )
            except ConfigError as e:
                note = f"majority baseline skipped: {e} (give majority_train=DATASET_DIR with a train split)"
                print(note, file=sys.stderr)
                log_lines.append(note)
        elif b == "blind":
            if analyzer is None:
                continue  # needs a model to blindfold
            results[ev.BLIND] = ev.score(
                recs,
                ev.model_predictions(
                    analyzer, cfg.dataset_dir, recs, traj, blind=True, progress=cfg.progress, batch_size=cfg.batch_size
                ),
                traj,
            )


def _score_external(
    cfg: Any, recs: list[dict], traj: dict[str, dict], results: dict[str, dict], log_lines: list[str]
) -> None:
    """Score the external endpoint's answers into `results` when external.enabled."""
    from labrobfail_vlm.bench import evaluate as ev

    if cfg.external.enabled:
        from labrobfail_vlm.llm_client import ChatClient

        client = ChatClient(cfg.external.base_url, cfg.external.model, cfg.external.api_key_env, cfg.external.timeout_s)
        ext = ev.external_predictions(client, cfg.dataset_dir, recs, cfg.progress, log_lines.append)
        results[str(cfg.external.name)] = ev.score(recs, ext, traj, log_lines.append)


def _results_markdown(cfg: Any, recs: list[dict], results: dict[str, dict], name: str) -> str:
    """results.md's tables: paper-comparable rows (with the paper's own), all-trajectory rows and detection."""
    from labrobfail_vlm import questions as Q
    from labrobfail_vlm.bench.report import (
        PAPER_ROWS,
        detected_markdown,
        detection_markdown,
        markdown,
        paper_row,
        paper_unseen_row,
        row,
    )

    fo = results[name]["failure_only"]
    rows = {k: paper_row(v) for k, v in results.items()}
    unseen_row = paper_unseen_row(cfg.split)
    if cfg.reference_rows and (cfg.split == "test" or unseen_row):
        # the paper's rows for the same setting (its unseen table has LabRobFail-VLM only)
        rows.update({"LabRobFail-VLM (paper)": unseen_row} if unseen_row else PAPER_ROWS)
    md = markdown(
        rows,
        f"LabRobFail-Bench, split {cfg.split}: paper-comparable (Q1, Q2 over all "
        f"{len({Q.traj_of(r['id']) for r in recs})} trajectories; Q3-Q6 "
        f"over the {fo['trajectories']} failed ones)",
    )
    md += "\n" + markdown(
        {k: row(v) for k, v in results.items()},
        f"All-trajectory scores (Q3-Q6 over successes too, where the answer is None; not "
        f"comparable with the paper), {len(recs)} records",
    )
    md += "\n" + detection_markdown(results, "Failure detection as a score: P(failure) for Q2")
    md += "\n" + detected_markdown(results)
    return md


def _executable_markdown(executable_rows: dict[str, dict]) -> str:
    """results.md's table of executable correction accuracy."""
    return (
        "\nExecutable correction accuracy (simulated: replay to the failure, run the correction, finish)\n\n"
        "| Corrections | Fixed | Failures | Accuracy (%) | Mapped (%) |\n|---|---|---|---|---|\n"
        + "".join(
            f"| {k} | {v['success']} | {v['failures']} | {v['accuracy']} | {v['mapped']} |\n"
            for k, v in executable_rows.items()
        )
    )


def _write_pngs(out: Path, split: str, results: dict[str, dict], name: str) -> None:
    """reliability_q2.png (every row with detection scores) and the main row's Q2, Q4, Q5 confusion matrices."""
    from labrobfail_vlm.bench.detection import reliability_png
    from labrobfail_vlm.bench.report import confusion_png

    main_res = results[name]
    curves = {k: v["detection"] for k, v in results.items() if v.get("detection")}
    if curves:
        reliability_png(curves, f"Q2 reliability, split {split}", out / "reliability_q2.png")
    from labrobfail_vlm.taxonomy import Severity

    sev_names = {str(s.value): f"{s.value} {s.title.removesuffix(' Level')} / {s.main_text}" for s in Severity}
    for d in ("Q2", "Q4", "Q5"):
        if main_res["confusion"][d]:
            confusion_png(
                main_res["confusion"][d],
                f"{d} confusion ({name})",
                out / f"confusion_{d.lower()}.png",
                sev_names if d == "Q4" else None,
            )


def main(argv: list[str]) -> int:
    from labrobfail_vlm.bench import evaluate as ev
    from labrobfail_vlm.io import atomic_write_bytes, atomic_write_json

    cfg = load_config("evaluate.yaml", argv)
    _check_args(cfg)
    if cfg.mode == "online":
        return _online(cfg)
    recs, traj = ev.load_split(cfg.dataset_dir, cfg.split, cfg.max_trajectories)
    if not recs:  # a table of dashes would read as a bench that ran
        raise ConfigError(f"split: {cfg.split} has no records in {cfg.dataset_dir}")
    threshold = val_threshold(cfg.model, cfg.dataset_dir) if cfg.threshold == "val" else float(cfg.threshold)
    out = _out_dir(cfg)
    log_lines: list[str] = []
    results: dict[str, dict] = {}
    analyzer, name, preds, tmpl = _predict(cfg, recs, traj, results, threshold)
    _write_predictions(out, preds)
    results = {name: ev.score(recs, preds, traj, log_lines.append), **results}
    _score_baselines(cfg, recs, traj, analyzer, results, log_lines)
    _score_external(cfg, recs, traj, results, log_lines)
    executable_rows = {}
    if cfg.executable.enabled:
        executable_rows = q6_executable(
            cfg, recs, traj, {name: preds, **({name + ", Q6 template": tmpl} if tmpl else {})}
        )
        for k, v in executable_rows.items():
            if k in results:
                results[k]["q6_executable"] = v
    main_res = results[name]
    bias = getattr(analyzer, "option_bias", None)  # fitted on validation (labrobfail-calibrate), from the checkpoint
    score = getattr(analyzer, "failure_score", "q2")  # how P(failure) was read (labrobfail_vlm/failure_score.py)
    md = _results_markdown(cfg, recs, results, name)
    payload = {
        **main_res,
        "split": cfg.split,
        "method": name,
        **(
            {"threshold": threshold, "threshold_chosen_on": "val" if cfg.threshold == "val" else "given"}
            if cfg.model is not None
            else {}
        ),
        **({"option_bias": {k: list(v) for k, v in bias.items()}} if bias else {}),
        **({"failure_score": score} if score != "q2" else {}),
        "baselines": {k: v for k, v in results.items() if k != name},
    }
    if executable_rows:
        payload["q6_executable_gold"] = executable_rows["gold corrections"]
        md += _executable_markdown(executable_rows)
    atomic_write_json(out / "results.json", payload)
    atomic_write_bytes(out / "results.md", md.encode())
    source = str(cfg.model or cfg.predictions or cfg.endpoint)
    if cfg.threshold != 0.5:  # the ledger says which operating point a sealed look was at
        source += f" at P(failure) >= {threshold:.4g}" + (" (chosen on val)" if cfg.threshold == "val" else "")
    if bias:
        source += " with option biases on " + ", ".join(bias)
    if score != "q2":
        source += f", P(failure) from {score}"
    ev.count_sealed_run(cfg.dataset_dir, cfg.split, source, main_res)
    atomic_write_bytes(out / "unparseable.log", "\n".join(log_lines).encode())
    _write_pngs(out, cfg.split, results, name)
    print(md)
    return 0


def _online(cfg: Any) -> int:
    """mode=online (labrobfail_vlm/bench/online.py): a local model's alarm on prefix grids, per keyframe, beside the
    robot-signal monitors; without model=, the robot-signal monitors alone (out_dir= then required)."""
    from labrobfail_vlm.bench.online import check_delta, check_pair_shares, run_online, scored_apart
    from labrobfail_vlm.bench.online_page import online_md
    from labrobfail_vlm.io import atomic_write_bytes

    if cfg.predictions is not None or cfg.endpoint is not None:
        raise ConfigError("mode=online: give model=DIR (the alarm reads a local model's P(failure) on prefix grids)")
    if cfg.model is None and cfg.out_dir is None:
        raise ConfigError("mode=online: without model=, give out_dir= (the robot-signal monitors alone)")
    check_pair_shares(cfg.pair_shares)  # before the model loads
    check_delta(cfg.delta)
    apart = scored_apart(cfg)
    fa = _load_analyzer(cfg, cache=False)[0] if cfg.model is not None else None  # prefix grids all differ
    # a split of another dataset gets a folder of its own: never the model's bench of its own split
    out = Path(cfg.out_dir or Path(cfg.model) / f"eval_online_{cfg.split}{'_' + apart.name if apart else ''}")
    res = run_online(cfg, fa, out, apart)
    md = "\n".join(online_md(res))
    atomic_write_bytes(out / "online.md", (md + "\n").encode())
    # a sealed split scored or calibrated on is a look at it like an offline bench: counted in the ledger the page
    # lists (no offline figures to carry, so its cells read "-")
    from labrobfail_vlm.bench.evaluate import count_sealed_run

    who = cfg.model or "robot-signal monitors"
    scored_dir = cfg.scored_dataset or cfg.dataset_dir
    for role, split, where in (("scored", cfg.split, scored_dir), ("calibration", cfg.calibration, cfg.dataset_dir)):
        count_sealed_run(where, str(split), f"online, {role}: {who}", {})
    print(md)
    return 0


def q6_executable(cfg, recs: list[dict], traj: dict[str, dict], predictions: dict[str, dict[str, str]]) -> dict:
    """Executable correction accuracy, from the simulator side (imported by name: the core imports no simulator)."""
    import importlib

    try:
        mod = importlib.import_module("sim_backends.supervision.executable")
    except ImportError as e:
        raise ConfigError(f"executable.enabled: needs the simulator package sim_backends ({e})") from None
    return mod.executable_rows(cfg.executable, recs, traj, predictions)


def cli() -> None:
    """The `labrobfail-evaluate` console script."""
    cli_main(main, __doc__)
