"""Episode <-> Parquet row, atomic shard writes, and the dataset manifest.

One Parquet file per shard (HF `datasets` loads them with the "parquet" builder).
Images are PNG bytes in `images[view][keyframe]`; the state trace, task metadata
and keyframes are JSON strings so the schema stays fixed across tasks.
"""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path
from typing import Any, Iterable

import pyarrow as pa
import pyarrow.parquet as pq

from labrobfail_vlm.io import atomic_write_bytes
from labrobfail_vlm.taxonomy import ATOMIC_ACTIONS, FAILURE_TYPE_NAMES, HORIZONS, Category
from sim_backends.types import Episode

SCHEMA = pa.schema(
    [
        ("episode_id", pa.string()),
        ("pair_id", pa.string()),
        ("role", pa.string()),
        ("backend", pa.string()),
        ("task", pa.string()),
        ("scenario", pa.string()),
        ("variant", pa.string()),
        ("seed", pa.int64()),
        ("success", pa.bool_()),
        ("failure_type", pa.string()),
        ("category", pa.int8()),
        ("severity", pa.int8()),
        ("failure_keyframe", pa.int32()),
        ("onset_s", pa.float64()),  # the failure's onset in sim time (Labels.onset_s); shards before 29 Nov lack it
        ("evidence", pa.string()),
        ("actions", pa.list_(pa.string())),
        ("horizon", pa.string()),
        ("num_keyframes", pa.int32()),
        ("camera_names", pa.list_(pa.string())),
        ("images", pa.list_(pa.list_(pa.binary()))),
        ("state_trace", pa.string()),
        ("task_meta", pa.string()),
        ("keyframes", pa.string()),
        ("nominal_keyframes", pa.string()),
        ("perturbation", pa.string()),
        ("cameras", pa.string()),  # JSON [view][keyframe]: view + projection matrix, or null (Episode.cameras)
    ]
)
LABEL_COLUMNS = [
    "episode_id",
    "pair_id",
    "role",
    "scenario",
    "task",
    "success",
    "failure_type",
    "category",
    "severity",
    "actions",
    "horizon",
    "evidence",
    "perturbation",
]


def episode_row(ep: Episode) -> dict[str, Any]:
    lab = ep.labels
    return {
        "episode_id": ep.episode_id,
        "pair_id": ep.pair_id,
        "role": ep.role,
        "backend": ep.backend,
        "task": ep.task,
        "scenario": ep.scenario,
        "variant": ep.variant,
        "seed": ep.seed,
        "success": lab.success,
        "failure_type": lab.failure_type,
        "category": lab.category,
        "severity": lab.severity,
        "failure_keyframe": lab.failure_keyframe,
        "onset_s": lab.onset_s,
        "evidence": lab.evidence,
        "actions": ep.actions,
        "horizon": ep.horizon,
        "num_keyframes": len(ep.executed_keyframes),
        "camera_names": ep.camera_names,
        "images": ep.images,
        "state_trace": json.dumps(ep.state_trace, separators=(",", ":")),
        "task_meta": ep.task_meta.to_json(),
        "keyframes": json.dumps([k.to_dict() for k in ep.executed_keyframes]),
        "nominal_keyframes": json.dumps([k.to_dict() for k in ep.nominal_keyframes]),
        "perturbation": json.dumps(ep.perturbation),
        "cameras": json.dumps(ep.cameras, separators=(",", ":")),
    }


def write_shard(path: Path, rows: list[dict[str, Any]], schema: pa.Schema = SCHEMA) -> None:
    """Write rows as one zstd Parquet file whole or not at all (labrobfail_vlm.io.atomic_write_bytes): a killed run
    never leaves a truncated shard, only a '*.tmp' file, which generate.py's resume deletes."""
    sink = pa.BufferOutputStream()
    pq.write_table(pa.Table.from_pylist(rows, schema=schema), sink, compression="zstd")
    atomic_write_bytes(path, sink.getvalue().to_pybytes())


def read_labels(paths: Iterable[Path]) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    for p in sorted(paths):
        rows.extend(pq.read_table(p, columns=LABEL_COLUMNS).to_pylist())
    return rows


def draw_summary(records: list[dict[str, Any]] | None) -> dict[str, Any]:
    """Nominal redraws and left-out failures of a run (the generator's per-shard records)."""
    if records is None:  # shards written before the records existed
        return {"nominal_redraws": None, "left_out": None}
    red = [r for r in records if r["kind"] == "nominal_redraw"]
    out = [r for r in records if r["kind"] == "left_out"]
    return {
        "nominal_redraws": {
            "count": len(red),
            "by_reason": dict(Counter(r["reason"] for r in red)),
            "by_scenario": dict(sorted(Counter(r["scenario"] for r in red).items())),
        },
        "left_out": {
            "count": len(out),
            "by_scenario": dict(sorted(Counter(r["scenario"] for r in out).items())),
            "records": [
                {k: r[k] for k in ("pair", "scenario", "seed", "draw", "perturbation", "evidence")} for r in out
            ],
        },
        "pairs_given_up": sum(r["kind"] == "given_up" for r in records),
    }


def injection_summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """What the injected episodes drew, against the paper's formulas: draws and outcomes per operator, physics
    events per parameter and sign of delta, gripper faults per direction, and the draws the `min_norm` filter
    rejected. A draw that caused no failure shows up as a success of its operator."""
    ops: dict[str, Counter] = {}
    phys: dict[str, Counter] = {}
    flips: Counter[str] = Counter()
    rejected: Counter[str] = Counter()
    for r in rows:
        if r.get("role") != "injected" or not r.get("perturbation"):
            continue
        prov = json.loads(r["perturbation"])
        op = f"{prov.get('level', 'none')}:{prov.get('op', 'none')}"
        ops.setdefault(op, Counter())["success" if r["success"] else "failure"] += 1
        for ev in prov.get("events", []):
            phys.setdefault(ev["param"], Counter())["+" if ev.get("delta", ev["scale"] - 1) > 0 else "-"] += 1
        for f in prov.get("flipped", []):
            flips[f"to_{f['to']}" if isinstance(f, dict) else "to_open"] += 1  # older shards: closing faults only
        if prov.get("rejected"):
            rejected[prov["op"]] += int(prov["rejected"])
    return {
        "by_operator": {k: dict(v) for k, v in sorted(ops.items())},
        "physics_events": {k: dict(sorted(v.items())) for k, v in sorted(phys.items())},
        "gripper_faults": dict(sorted(flips.items())),
        "filter_rejections": dict(sorted(rejected.items())),
    }


def manifest(
    rows: list[dict[str, Any]], extra: dict[str, Any], records: list[dict[str, Any]] | None = None
) -> dict[str, Any]:
    fails = [r for r in rows if not r["success"]]
    by_type = {t: 0 for t in FAILURE_TYPE_NAMES}
    by_type.update(Counter(r["failure_type"] for r in fails))
    by_cat = {c.name.lower(): 0 for c in Category}
    by_cat.update(Counter(Category(r["category"]).name.lower() for r in fails))
    by_action = {a: 0 for a in ATOMIC_ACTIONS}
    for r in rows:
        for a in set(r["actions"]):
            by_action[a] += 1
    by_h = {h: 0 for h in HORIZONS}
    by_h.update(Counter(r["horizon"] for r in rows))
    return {
        **extra,
        "episodes": len(rows),
        "pairs": len({r["pair_id"] for r in rows}),
        "by_outcome": {"success": len(rows) - len(fails), "failure": len(fails)},
        "by_category": by_cat,
        "by_failure_type": by_type,
        "by_severity": dict(sorted(Counter(str(r["severity"]) for r in fails).items())),
        "by_action": by_action,
        "by_horizon": by_h,
        "by_task": dict(sorted(Counter(r["scenario"] for r in rows).items())),
        "scenario_count": len({r["scenario"] for r in rows}),
        # A label is a guess when no detector explained it; the labeler no longer makes them (must stay 0).
        "guessed_labels": sum(
            1 for r in fails if r["failure_type"] is None or "no earlier signature" in (r["evidence"] or "")
        ),
        **draw_summary(records),
        "injection": injection_summary(rows),
    }
