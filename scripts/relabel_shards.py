"""Re-derive every label of a run's shards from their own state traces with the labeler as it stands now, into a new
folder: what a labeler change needs instead of a new generation (a shard keeps its trace and task metadata, so its
labels re-derive from it alone; sim_backends/labeler.py).

Run as:
    python scripts/relabel_shards.py shards=outputs/reproduce/shards out=outputs/relabelled/shards

`shards` is a folder of variant folders (each with run.json, manifest.json and shard-*.parquet, as
labrobfail-generate writes them) or one variant folder. Each shard is rewritten whole, atomically, with the label
columns (success, failure type, category, severity, failure keyframe, onset, evidence) re-derived; every other column
is copied. A shard already in `out` is kept, so a stopped run goes on. Each variant's manifest gets its label counts
recounted and a `relabelled` entry: where from, and how many episodes changed in each label column; the summary is
also written to out/relabel.json. An episode whose outcome would change, or that no detector would explain any more,
stops the run: its pair was drawn (and redrawn) on its old outcome, so it needs a new generation, not a relabel.
"""

from __future__ import annotations

import json
import shutil
from collections import Counter
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
from tqdm import tqdm

from labrobfail_vlm.config import ConfigError, cli_main, load_config
from labrobfail_vlm.io import atomic_write_json
from sim_backends.labeler import derive_labels
from sim_backends.shards import SCHEMA, manifest, write_shard

DEFAULTS = """
shards: outputs/reproduce/shards   # a folder of variant folders, or one variant folder
out: null                          # the new folder (never the one read)
progress: true
"""

LABELS = ("success", "failure_type", "category", "severity", "failure_keyframe", "onset_s", "evidence")
# the manifest's counts that follow the labels (sim_backends/shards.manifest); the rest describes the generation
COUNTED = ("by_outcome", "by_category", "by_failure_type", "by_severity", "guessed_labels")
COUNTED_FROM = ("pair_id", "actions", "horizon", "scenario", "perturbation")  # what else shards.manifest reads


def relabel_row(row: dict[str, Any]) -> dict[str, Any]:
    """The row with its label columns re-derived from its trace and task metadata."""
    lab = derive_labels(json.loads(row["state_trace"]), json.loads(row["task_meta"]))
    if lab.success != row["success"]:
        raise ConfigError(
            f"episode {row['episode_id']}: the labeler now says {'success' if lab.success else 'failure'} "
            "(its pair was drawn on the old outcome: generate again instead)"
        )
    if not lab.success and lab.failure_type is None:
        raise ConfigError(f"episode {row['episode_id']}: no detector explains its failure any more ({lab.evidence})")
    return row | {k: getattr(lab, k) for k in LABELS}


def relabel_variant(src: Path, dst: Path, progress: bool) -> dict[str, int]:
    """One variant folder: its shards relabelled into dst, its manifest recounted; per label column, how many
    episodes changed."""
    dst.mkdir(parents=True, exist_ok=True)
    changed: Counter[str] = Counter()
    rows_all: list[dict[str, Any]] = []
    files = sorted(src.glob("shard-*.parquet"))
    for f in tqdm(files, desc=src.name, disable=not progress):
        old = pq.read_table(f).to_pylist()
        out = dst / f.name
        new = pq.read_table(out).to_pylist() if out.exists() else [relabel_row(r) for r in old]
        for a, b in zip(old, new):
            changed.update(k for k in LABELS if a[k] != b[k])
        if not out.exists():
            write_shard(out, new, SCHEMA)
        rows_all.extend({k: r[k] for k in (*LABELS, *COUNTED_FROM)} for r in new)
    for extra in sorted(src.iterdir()):  # run.json, rejects; the manifest is rewritten below
        if extra.is_file() and extra.suffix != ".parquet" and extra.name != "manifest.json":
            shutil.copy2(extra, dst / extra.name)
    meta = json.loads((src / "manifest.json").read_text())
    fresh = manifest(rows_all, {})
    meta |= {k: fresh[k] for k in COUNTED}
    meta["relabelled"] = {"from": str(src), "changed": dict(sorted(changed.items()))}
    atomic_write_json(dst / "manifest.json", meta)
    return dict(sorted(changed.items())) | {"episodes": len(rows_all)}


def main(argv: list[str]) -> int:
    cfg = load_config(DEFAULTS, argv)
    src = Path(str(cfg.shards))
    if cfg.out is None:
        raise ConfigError("out: give the new folder (out=DIR); the shards read are never rewritten")
    out = Path(str(cfg.out))
    if not src.is_dir():
        raise ConfigError(f"shards: no folder {src}")
    if out.resolve() == src.resolve():
        raise ConfigError(f"out: {out} is the folder read; relabel into a new one")
    variants = [src] if (src / "run.json").exists() else sorted(p for p in src.iterdir() if (p / "run.json").exists())
    if not variants:
        raise ConfigError(f"shards: {src} holds no variant folder (run.json)")
    summary = {v.name: relabel_variant(v, out if v == src else out / v.name, bool(cfg.progress)) for v in variants}
    atomic_write_json(out / "relabel.json", summary)
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    cli_main(main, __doc__)
