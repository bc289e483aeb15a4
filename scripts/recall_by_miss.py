"""Where a model's missed failures lie: Q2 recall on a split's failed trajectories by which goals failed at the end,
and, for those whose only failed goals are "at" goals (an object set down off its zone), by how far it missed, per
goal tolerance (a placed object's 0.04 m, a tube's 0.012), with the offset that miss makes, in pixels, in each view
where it is in the picture at the last recorded keyframe. Seen and validation splits only (never a sealed one).

Run as:
    python scripts/recall_by_miss.py run=outputs/reproduce bench=outputs/reproduce/train/final/eval_val split=val

Reads <run>/dataset (the split's records and trajectories), the shards of every folder under <run>/shards (each
failure's state trace, task meta and camera matrices, matched by variant and episode) and <bench>/predictions.jsonl
(a failure is caught when its Q2 reply says it failed, as the bench counts it); writes <bench>/recall_by_miss.json.
The miss is read from the simulator's final state like every label; nothing here is chosen on it."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from labrobfail_data.build import _rows
from labrobfail_data.frame_targets import project
from labrobfail_vlm import questions as Q
from labrobfail_vlm.bench.evaluate import called_failed, load_split, read_predictions
from labrobfail_vlm.config import ConfigError, cli_main, load_config
from labrobfail_vlm.io import atomic_write_json
from labrobfail_vlm.taxonomy import SEALED_SPLITS
from sim_backends.goals import failed_goals, final, place_xy

DEFAULTS = """
run: outputs/reproduce        # a make reproduce folder: dataset/ and shards/
bench: null                   # a bench folder of that dataset (labrobfail-evaluate's eval_<split>)
split: val                    # the split the bench scored
edges: [0.04, 0.06, 0.08, 0.12]   # m: miss bins, per goal tolerance (a placed object's 0.04, a tube's 0.012)
"""

COLUMNS = ["episode_id", "variant", "state_trace", "task_meta", "cameras", "camera_names"]


def at_miss(trace: dict, meta: dict) -> tuple[list[str], float | None, dict | None]:
    """(the kinds of goal that failed at the end, the largest horizontal miss of a failed "at" goal in m or None,
    that goal). Each goal has its own tolerance (a placed object 0.04 m, a tube in its rack hole 0.012); an "at" goal
    can also fail on height (the object below the bench top) with its miss within that tolerance."""
    failed = failed_goals(trace, meta)
    worst, goal = None, None
    for g in failed:
        if g["kind"] == "at":
            miss = float(np.linalg.norm(np.asarray(final(trace, f"{g['object']}.pos"))[:2] - place_xy(meta, g["xy"])))
            if worst is None or miss > worst:
                worst, goal = miss, g
    return sorted({g["kind"] for g in failed}), worst, goal


def pixel_offsets(row: dict, trace: dict, meta: dict, goal: dict, size: int) -> dict[str, float]:
    """Per view with camera matrices at its last recorded keyframe: the pixel distance between where the object
    rests and where it would rest on its zone's centre (at the same height), where both are in that picture (the
    moving wrist camera, the one view that is not fixed, mostly looks elsewhere by then)."""
    pos = np.asarray(final(trace, f"{goal['object']}.pos"), float)
    on_zone = np.r_[place_xy(meta, goal["xy"]), pos[2]]
    out = {}
    for name, mats in zip(row["camera_names"], json.loads(row.get("cameras") or "[]")):
        last = next((m for m in reversed(mats or []) if m is not None), None)
        if last is not None:
            a, b = project(np.stack([pos, on_zone]), last, size)
            # both in the picture (a point behind the camera projects to NaN, which fails the test)
            if np.all((a >= 0) & (a <= size)) and np.all((b >= 0) & (b <= size)):
                out[name] = float(np.linalg.norm(a - b))
    return out


def shard_rows(run: Path, wanted: set[tuple[str, str]]) -> tuple[dict[tuple[str, str], dict], int]:
    """The shard rows of the wanted (variant, episode) pairs, and the image size the shards were rendered at."""
    rows, sizes = {}, set()
    for run_json in sorted((run / "shards").glob("*/run.json")):
        found = False
        # the dataset builder's reader: a corrupt shard or one lacking a column is a one-line error
        for r in _rows(sorted(run_json.parent.glob("shard-*.parquet")), COLUMNS):
            key = (r["variant"], r["episode_id"])
            if key in wanted:
                if key in rows:
                    raise ConfigError(f"run: episode {key[1]} of {key[0]} is in two shard folders under {run}")
                rows[key], found = r, True
        if found:  # only the folders the split's failures come from
            try:
                sizes.add(int(json.loads(run_json.read_text())["image_size"]))
            except (ValueError, KeyError, TypeError):
                raise ConfigError(f"run: {run_json} has no readable image_size") from None
    if len(sizes) > 1:
        raise ConfigError(f"run: shards rendered at several image sizes {sorted(sizes)}")
    return rows, sizes.pop() if sizes else 0


def tally(items: list[dict], key) -> dict[str, dict[str, int]]:
    out: dict[str, dict[str, int]] = {}
    for it in items:
        c = out.setdefault(key(it), {"n": 0, "caught": 0})
        c["n"] += 1
        c["caught"] += int(it["caught"])
    return out


def goal_group(it: dict) -> str:
    if it["kinds"] != ["at"]:
        return "other goals" if it["kinds"] else "none"
    return "at only, on height" if it["height_only"] else "at only"


def miss_bins(items: list[dict], edges: list[float]) -> list[dict[str, Any]]:
    """At-only failures of one tolerance by miss, in bins (0, e0], (e0, e1], ..., (e_last, inf)."""
    bins = []
    for lo, hi in zip([0.0, *edges], [*edges, float("inf")]):
        s = [it for it in items if lo < it["miss_m"] <= hi]
        views = sorted({v for it in s for v in it["offset_px"]})
        bins.append(
            {
                "miss_m": [lo, None if hi == float("inf") else hi],
                "n": len(s),
                "caught": sum(it["caught"] for it in s),
                "types": dict(Counter(it["type"] for it in s)),
                "median_offset_px": {
                    v: float(np.median([it["offset_px"][v] for it in s if v in it["offset_px"]])) for v in views
                },
            }
        )
    return bins


def summarise(items: list[dict], edges: list[float]) -> dict[str, Any]:
    """Recall by failed goals; at-only failures that missed on distance by miss, per goal tolerance (m)."""
    by_miss = {}
    for tol in sorted({it["tol_m"] for it in items if goal_group(it) == "at only"}):
        same = [it for it in items if goal_group(it) == "at only" and it["tol_m"] == tol]
        by_miss[f"{tol:g}"] = miss_bins(same, edges)
    return {
        "failures": len(items),
        "caught": sum(it["caught"] for it in items),
        "by_failed_goals": tally(items, goal_group),
        "at_only_by_miss": by_miss,
        "by_type": tally(items, lambda it: it["type"]),
    }


def main(argv: list[str]) -> int:
    cfg = load_config(DEFAULTS, argv)
    if cfg.bench is None:
        raise ConfigError("bench: give the bench folder whose predictions.jsonl to read (bench=DIR)")
    run, bench = Path(str(cfg.run)), Path(str(cfg.bench))
    try:
        edges = [float(e) for e in cfg.edges]
    except (TypeError, ValueError):
        edges = []
    if not edges or edges != sorted(edges) or edges[0] <= 0:
        raise ConfigError(f"edges: expected an increasing list of metres > 0, got {cfg.edges!r}")
    if str(cfg.split) in SEALED_SPLITS:  # an analysis to choose by: never on a sealed split
        raise ConfigError(f"split: {cfg.split} is sealed; read a seen or validation split")
    recs, traj = load_split(run / "dataset", str(cfg.split))
    caught = called_failed(recs, read_predictions(bench / "predictions.jsonl"))
    # whole trajectories only: a prefix grid (a dataset built with prefix cuts) ends before its episode does
    whole = {t for t, m in traj.items() if not m["success"] and "prefix_of" not in m}
    failed = sorted({Q.traj_of(r["id"]) for r in recs} & whole)
    key = {t: (traj[t]["variant"], t.split("-", 1)[1]) for t in failed}
    rows, size = shard_rows(run, set(key.values()))
    missing = [t for t in failed if key[t] not in rows]
    if missing:
        raise ConfigError(
            f"run: {len(missing)} failed trajectories have no shard row under {run / 'shards'} (first {missing[0]})"
        )
    items = []
    for t in failed:
        row = rows[key[t]]
        trace, meta = json.loads(row["state_trace"]), json.loads(row["task_meta"])
        kinds, miss, goal = at_miss(trace, meta)
        items.append(
            {
                "trajectory": t,
                "type": traj[t]["failure_type"],
                "scenario": traj[t]["scenario"],
                "kinds": kinds,
                "miss_m": miss,
                "tol_m": None if goal is None else float(goal["tol"]),
                "height_only": goal is not None and miss <= goal["tol"],
                "caught": t in caught,
                "offset_px": pixel_offsets(row, trace, meta, goal, size) if goal is not None else {},
            }
        )
    out = {"split": str(cfg.split), "bench": str(bench), **summarise(items, edges), "trajectories": items}
    atomic_write_json(bench / "recall_by_miss.json", out)
    print(f"{cfg.split}: {out['caught']} of {out['failures']} failures caught")
    for name, c in out["by_failed_goals"].items():
        print(f"  {name}: {c['caught']} of {c['n']}")
    for tol, bins in out["at_only_by_miss"].items():
        for b in bins:
            px = ", ".join(f"{v} {p:.1f} px" for v, p in b["median_offset_px"].items())
            lo, hi = b["miss_m"]
            print(f"  at only (tolerance {tol} m), miss {lo}-{hi or 'inf'} m: {b['caught']} of {b['n']} ({px})")
    return 0


if __name__ == "__main__":
    cli_main(main, __doc__)
