"""Executable correction accuracy (beyond the paper): does the correction, run in the simulator, fix the failure?

For each failed trajectory of a bench split: rebuild its initial state (scenario, seed, variant from the
shard the dataset was built from), replay its executed keyframes up to the labeled failure keyframe (with
its physics perturbation), run the correction's primitives (labrobfail_vlm/actions.py ->
sim_backends/executor.py), continue the nominal plan after the keyframe nearest to the arm (the scripted
policy's re-planning rule), and count the episode's success. The gold corrections bound what a model's
corrections can reach; a correction that does not map (a `manual` phrase) counts as not executed.
"""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path
from typing import Any, Iterable, Sequence

import pyarrow.parquet as pq

from labrobfail_vlm.actions import executable, to_primitives
from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.questions import traj_of
from sim_backends.executor import CorrectionExecutor
from sim_backends.perturbations.physics import events_from_record
from sim_backends.policies.scripted import resume_index
from sim_backends.source import FailureSource
from sim_backends.types import Keyframe

SHARD_COLUMNS = ["episode_id", "variant", "scenario", "seed", "keyframes", "perturbation"]


def shard_index(dirs: Iterable[str | Path]) -> dict[str, dict[str, Any]]:
    """Shard rows by trajectory id ("<variant>-<episode_id>", as labrobfail_data/annotate.py names them)."""
    out: dict[str, dict[str, Any]] = {}
    for d in dirs:
        files = sorted(Path(d).glob("shard-*.parquet"))
        if not files:
            raise ConfigError(f"executable.shards: no shard-*.parquet in {d!r}")
        for f in files:
            for r in pq.read_table(f, columns=SHARD_COLUMNS).to_pylist():
                out[f"{r['variant']}-{r['episode_id']}"] = r
    return out


def run_correction(
    src: FailureSource, row: dict[str, Any], failure_keyframe: int, text: str, objects: Sequence[str]
) -> dict[str, Any]:
    """Replay `row` to its failure keyframe, execute `text`, finish the plan; the outcome."""
    prims = to_primitives(text, objects)
    if not executable(prims):
        return {"success": False, "mapped": False, "executed": False, "reason": "does not map to primitives"}
    src.reset(row["scenario"], int(row["seed"]), row["variant"])
    plan = src.scripted_keyframes()
    src.begin(events_from_record(json.loads(row["perturbation"] or "{}")))
    for kd in json.loads(row["keyframes"])[: failure_keyframe + 1]:
        src.step(Keyframe.from_dict(kd))
    res = CorrectionExecutor(src).run(prims, final=True)  # any step not run counts as left out, as it always has
    if res.executed:
        for kf in plan[resume_index(plan, src.observe().state, res.step) :]:
            src.step(kf)
    ep = src.finish()
    return {
        "success": bool(ep.labels.success),
        "mapped": True,
        "executed": res.executed,
        "reason": res.error or "",
        "failure_type": ep.labels.failure_type,
    }


def executable_accuracy(
    src: FailureSource,
    shards: dict[str, dict[str, Any]],
    traj: dict[str, dict[str, Any]],
    corrections: dict[str, dict[str, str]],
    limit: int | None = None,
) -> dict[str, Any]:
    """`corrections`: name ("gold", a model row) -> {trajectory: correction text}. Per name: successes over the
    failed trajectories that have a shard row, the mapped fraction, and a breakdown per failure type."""
    failed = sorted(t for t, m in traj.items() if not m.get("success", True) and "prefix_of" not in m)
    failed = [t for t in failed if t in shards and any(t in c for c in corrections.values())][:limit]
    out: dict[str, Any] = {}
    for name, texts in corrections.items():
        rows = []
        for t in failed:
            if t not in texts:
                continue
            try:
                r = run_correction(
                    src, shards[t], int(traj[t]["failure_keyframe"]), texts[t], traj[t].get("objects", [])
                )
            except ValueError as e:  # a shard row this code cannot replay: name it, no traceback
                raise ConfigError(f"executable.shards: trajectory {t}: {e}") from None
            rows.append((traj[t]["failure_type"], r))
        n = len(rows)
        ok = sum(r["success"] for _, r in rows)
        by = Counter(ft for ft, _ in rows)
        out[name] = {
            "success": ok,
            "failures": n,
            "accuracy": round(100.0 * ok / n, 2) if n else None,
            "mapped": round(100.0 * sum(r["mapped"] for _, r in rows) / n, 2) if n else None,
            "executed": round(100.0 * sum(r["executed"] for _, r in rows) / n, 2) if n else None,
            "by_type": {
                ft: round(100.0 * sum(r["success"] for f, r in rows if f == ft) / c, 2) for ft, c in sorted(by.items())
            },
        }
    return out


def q6_texts(recs: list[dict[str, Any]], preds: dict[str, str] | None = None) -> dict[str, str]:
    """trajectory -> Q6 text: the gold answers, or a prediction set's."""
    out = {}
    for r in recs:
        if r["id"].endswith("_Q6"):
            t = traj_of(r["id"])
            text = r["conversations"][1]["value"] if preds is None else preds.get(r["id"])
            if text is not None:
                out[t] = text
    return out


def executable_rows(ex: Any, recs: list[dict], traj: dict[str, dict], predictions: dict[str, dict[str, str]]) -> dict:
    """Executable correction accuracy of each prediction set and of the gold corrections, for the bench
    (`labrobfail-evaluate executable.enabled=true`; `ex` is its `executable` section)."""
    from sim_backends.registry import available_backends, make_backend

    if not ex.shards:
        raise ConfigError("executable.shards: name the shard folder(s) the dataset was built from")
    if ex.backend not in available_backends():
        raise ConfigError(f"executable.backend: unknown backend {ex.backend!r}")
    dirs = [ex.shards] if isinstance(ex.shards, str) else list(ex.shards)
    for d in dirs:
        if not Path(d).is_dir():
            raise ConfigError(f"executable.shards: no such folder {d!r}")
    shards = shard_index(dirs)
    texts = {k: q6_texts(recs, p) for k, p in predictions.items()}
    texts["gold corrections"] = q6_texts(recs)
    try:
        src = make_backend(ex.backend, render=False)  # no cameras needed
    except TypeError:
        src = make_backend(ex.backend)
    try:
        return executable_accuracy(src, shards, traj, texts, ex.limit)
    finally:
        src.close()
