"""Tower pretraining data: simulator shards -> per-trajectory frames and dense per-frame targets.

One output file per source shard (`frames-<variant>-<shard>-<signature>-<made>.parquet`, written atomically; a
rerun skips the files already written, so a killed build resumes; the signature names the target definitions and
grid, so a changed definition rebuilds instead of mixing, and <made> the shard's size and time, so a regenerated
shard is read again), then `index.json`: the files, the target names, and each pair's split.
A row is one trajectory: the PNG bytes of the keyframes a grid of `max_frames` shows, in every rendered view
(`images[view][frame]`), and its targets from labrobfail_data/frame_targets.py (cells (F, V, K) and points
(F, V, C, P, 2) as float32 bytes). Seen pairs are split train/val by `ratios` (labrobfail_data/splits.py, grouped by
pair, so no held-out frame has a training twin); held-out variants are evaluation sets only: the tower never trains
on them.
"""

from __future__ import annotations

import json
import zlib
from collections import Counter
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from omegaconf import DictConfig
from tqdm import tqdm

from labrobfail_data.annotate import grid_failure_frame, grid_picks
from labrobfail_data.build import READ_COLUMNS, _rows, _shard_files, check_unique, fractions
from labrobfail_data.frame_targets import CELL_TARGETS, MAX_POINTS, TOKEN_TARGETS, row_targets
from labrobfail_data.splits import assign
from labrobfail_vlm.config import ConfigError, make_dir, require_ints
from labrobfail_vlm.io import atomic_write_json
from sim_backends.shards import write_shard

READ = [*READ_COLUMNS, "cameras"]  # the dataset's columns and the camera matrices (token targets)
SCHEMA = pa.schema(
    [
        ("trajectory", pa.string()),
        ("group", pa.string()),
        ("variant", pa.string()),
        ("scenario", pa.string()),
        ("success", pa.bool_()),
        ("failure_type", pa.string()),
        ("failure_frame", pa.int32()),
        ("frames", pa.int32()),
        ("views", pa.list_(pa.string())),
        ("images", pa.list_(pa.list_(pa.binary()))),
        ("cells", pa.binary()),
        ("points", pa.binary()),
    ]
)


def _record(row: dict[str, Any], max_frames: int, image_size: int) -> dict[str, Any]:
    picks = grid_picks(row, max_frames)
    views = list(row["camera_names"])
    if any(not row["images"][v][k] for v in range(len(views)) for k in picks):
        raise ConfigError(
            f"shards: episode {row['episode_id']} lacks images of the keyframes a {max_frames}-frame "
            f"grid shows (generate with render_frames={max_frames})"
        )
    frame = grid_failure_frame(row, picks)
    cells, points = row_targets(row, picks, range(len(views)), frame, image_size)
    return {
        "trajectory": f"{row['variant']}-{row['episode_id']}",
        "group": f"{row['variant']}-{row['pair_id']}",
        "variant": row["variant"],
        "scenario": row["scenario"],
        "success": bool(row["success"]),
        "failure_type": row["failure_type"],
        "failure_frame": frame,
        "frames": len(picks),
        "views": views,
        "images": [[row["images"][v][k] for k in picks] for v in range(len(views))],
        "cells": cells.astype(np.float32).tobytes(),
        "points": points.astype(np.float32).tobytes(),
    }


def build(cfg: DictConfig) -> dict[str, Any]:
    """cfg: shards (dir or list), out_dir, max_frames, image_size, ratios [train, val], seed, progress."""
    files = _shard_files(cfg)
    max_frames, size = int(cfg.max_frames), int(cfg.image_size)
    if max_frames < 1 or size < 32:
        raise ConfigError(f"max_frames/image_size: expected >= 1 and >= 32, got {max_frames}, {size}")
    ratios = fractions("data.ratios", cfg.ratios, 2, whole=False)  # before a frame file is written
    require_ints(cfg, ("seed",), 0, "data.")
    check_unique(files)  # two runs numbered alike would merge two pairs into one split group
    out = make_dir("data.out_dir", cfg.out_dir)
    sig = f"{zlib.crc32(json.dumps([CELL_TARGETS, TOKEN_TARGETS, MAX_POINTS, max_frames, size]).encode()):08x}"
    written: list[str] = []
    for f in tqdm(files, desc="tower data", disable=not cfg.progress):
        st = f.stat()  # a shard regenerated under the same name (another seed) is read again, not served stale
        made = f"{zlib.crc32(f'{st.st_size}:{st.st_mtime_ns}'.encode()):08x}"
        name = f"frames-{f.parent.name}-{f.stem}-{sig}-{made}.parquet"
        target = out / name
        if not target.is_file():
            recs = [_record(r, max_frames, size) for r in _rows([f], READ)]
            write_shard(target, recs, SCHEMA)
        written.append(name)
    meta = [
        r
        for n in written
        for r in pq.read_table(out / n, columns=["group", "variant", "success", "failure_type"]).to_pylist()
    ]
    split = assign(((r["group"], r["variant"]) for r in meta), int(cfg.seed), (ratios[0], ratios[1], 0.0))
    counts = Counter(split[r["group"]] for r in meta)
    index = {
        "files": written,
        "cell_targets": list(CELL_TARGETS),
        "token_targets": list(TOKEN_TARGETS),
        "max_points": MAX_POINTS,
        "max_frames": max_frames,
        "image_size": size,
        "split": split,
        "trajectories": dict(sorted(counts.items())),
        "failures": dict(Counter(split[r["group"]] for r in meta if not r["success"])),
        "shards": sorted({str(f.parent) for f in files}),
    }
    atomic_write_json(out / "index.json", index)
    return index
