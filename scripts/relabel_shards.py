"""Re-derive every label of a run's shards from their own state traces with the labeler as it stands now, into a new
folder: what a labeler change needs instead of a new generation (a shard keeps its trace and task metadata, so its
labels re-derive from it alone; sim_backends/labeler.py).

Run as:
    python scripts/relabel_shards.py shards=outputs/reproduce/shards out=outputs/relabelled/shards

`shards` is a folder of variant folders (each with run.json, manifest.json and shard-*.parquet, as
labrobfail-generate writes them) or one variant folder. Each shard is rewritten whole, atomically, with the label
columns (success, failure type, category, severity, failure keyframe, onset, evidence) re-derived; every other column
is copied. Every label is derived before anything is written (a refusal leaves `out` as it was), and every shard is
rewritten on each run (seconds to a minute: a rerun after a labeler fix is never stale). Each variant's manifest gets
its label counts recounted and a `relabelled` entry: where from, and how many episodes changed in each label
column; the summary is also written to out/relabel.json. An episode whose outcome would change, or that no detector
would explain any more, stops the run: its pair was drawn (and redrawn) on its old outcome, so it needs a new
generation, not a relabel.
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
    """The row's label columns re-derived from its trace and task metadata."""
    try:
        lab = derive_labels(json.loads(row["state_trace"]), json.loads(row["task_meta"]))
    except (KeyError, IndexError, TypeError, ValueError) as e:
        raise ConfigError(
            f"episode {row['episode_id']}: cannot re-derive its labels ({type(e).__name__}: {e})"
        ) from None
    if lab.success != row["success"]:
        raise ConfigError(
            f"episode {row['episode_id']}: the labeler now says {'success' if lab.success else 'failure'} "
            "(its pair was drawn on the old outcome: generate again instead)"
        )
    if not lab.success and lab.failure_type is None:
        raise ConfigError(f"episode {row['episode_id']}: no detector explains its failure any more ({lab.evidence})")
    return {k: getattr(lab, k) for k in LABELS}


def _shards(src: Path) -> list[Path]:
    """The variant's shards, each checked to hold the generator's columns (a rewrite keeps no other)."""
    if not (src / "manifest.json").is_file():
        raise ConfigError(f"shards: {src} has no manifest.json (not a variant folder labrobfail-generate finished)")
    files = sorted(src.glob("shard-*.parquet"))
    for f in files:
        try:
            names = pq.ParquetFile(f).schema_arrow.names
        except Exception as e:  # pyarrow raises several types for a corrupt file
            raise ConfigError(f"shards: cannot read {f} ({type(e).__name__}: {str(e).splitlines()[0]})") from None
        odd = sorted(set(names) ^ set(SCHEMA.names))
        if odd:
            raise ConfigError(f"shards: {f} differs from the shard schema in columns {odd}")
    return files


Relabelled = list[tuple[Path, list[dict[str, Any]]]]  # per shard file, each row's new label columns


def derive_variant(src: Path, progress: bool) -> Relabelled:
    """Per shard of a variant folder, each row's new label columns; nothing is written (a refusal leaves no output)."""
    cols = ["episode_id", "success", "state_trace", "task_meta"]
    return [
        (f, [relabel_row(r) for r in pq.read_table(f, columns=cols).to_pylist()])
        for f in tqdm(_shards(src), desc=src.name, disable=not progress)
    ]


def write_variant(src: Path, dst: Path, labels: Relabelled) -> dict[str, int]:
    """The variant's shards written to dst with their new labels (each whole, atomically; every shard rewritten, so
    a rerun after a labeler fix is never stale), its other files copied and its manifest recounted; per label
    column, how many episodes changed."""
    dst.mkdir(parents=True, exist_ok=True)
    changed: Counter[str] = Counter()
    counted: list[dict[str, Any]] = []
    for f, new in labels:
        rows = pq.read_table(f).to_pylist()
        for r, lab in zip(rows, new, strict=True):
            changed.update(k for k in LABELS if r[k] != lab[k])
            r.update(lab)
        write_shard(dst / f.name, rows, SCHEMA)
        counted.extend({k: r[k] for k in (*LABELS, *COUNTED_FROM)} for r in rows)
    for extra in sorted(src.iterdir()):  # run.json, rejects; not the manifest (below) nor a killed write's *.tmp
        if extra.is_file() and extra.suffix not in (".parquet", ".tmp") and extra.name != "manifest.json":
            shutil.copy2(extra, dst / extra.name)
    meta = json.loads((src / "manifest.json").read_text())
    fresh = manifest(counted, {})
    meta |= {k: fresh[k] for k in COUNTED}
    meta["relabelled"] = {"from": str(src), "changed": dict(sorted(changed.items()))}
    atomic_write_json(dst / "manifest.json", meta)
    return dict(sorted(changed.items())) | {"episodes": len(counted)}


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
    labels = {v: derive_variant(v, bool(cfg.progress)) for v in variants}  # every refusal before any write
    summary = {v.name: write_variant(v, out if v == src else out / v.name, labels[v]) for v in variants}
    atomic_write_json(out / "relabel.json", summary)
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    cli_main(main, __doc__)
