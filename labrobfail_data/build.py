"""LabRobFail-Data builder: shards -> grids + six-dimension VQA records -> filtered splits, exports, stats, plots.

Output layout (out_dir):
  images/<trajectory>.png            one keyframe grid per trajectory
  train.json val.json test.json      ShareGPT/LLaVA records (and val_*.json, test_*.json for held-out variants)
  dataset_info.json                  LLaMA-Factory's description of those files (sharegpt formatting)
  trajectories.json                  per-trajectory metadata (labels, split, sampled keyframes, strategy)
  robot_signals.parquet              the robot's own signals at every trace sample (the online bench's 40 Hz monitor)
  stats.json                         counts, filter report (drops by reason), split sizes
  plots/*.png                        horizon distribution, success/failure per task, types by category
  review.html                        the human-sampling page (labrobfail_data/review.py)
Every file is written atomically; a trajectory is kept only with all six records passing the filter.
"""

from __future__ import annotations

import dataclasses
import json
import zlib
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from labrobfail_data.annotate import PREFIX_QUESTIONS, Annotated, annotate, check_record, grid_failure_frame, grid_picks
from labrobfail_data.paraphrase import Paraphraser
from labrobfail_data.splits import assign
from labrobfail_vlm import drawing
from labrobfail_vlm import questions as Q
from labrobfail_vlm.bench import robot_baseline
from labrobfail_vlm.config import ConfigError, make_dir, names, require_ints
from labrobfail_vlm.grid import GridConfig
from labrobfail_vlm.io import atomic_write_bytes, atomic_write_json, save_image
from labrobfail_vlm.taxonomy import DATA_VARIANTS, HELD_OUT_SPLITS, RENAMED_VARIANTS, REPLAY_SPLITS, SEEN_SPLITS

READ_COLUMNS = [
    "episode_id",
    "pair_id",
    "variant",
    "scenario",
    "success",
    "failure_type",
    "category",
    "severity",
    "failure_keyframe",
    "evidence",
    "actions",
    "horizon",
    "images",
    "state_trace",
    "task_meta",
    "keyframes",
    "camera_names",
]


def _shard_dirs(cfg: DictConfig) -> list[str]:
    """The `shards` setting as a list of folders (one given alone, or a list); a ConfigError for anything else."""
    dirs = cfg.shards
    if dirs is None:
        raise ConfigError("shards: give a shard directory (shards=DIR) or a list of them")
    dirs = [dirs] if isinstance(dirs, str) else [str(d) for d in dirs] if OmegaConf.is_list(dirs) else None
    if dirs is None:
        raise ConfigError(f"shards: give a shard directory (shards=DIR) or a list of them, got {cfg.shards!r}")
    return dirs


def _shard_files(cfg: DictConfig) -> list[Path]:
    files: list[Path] = []
    for d in _shard_dirs(cfg):
        if not Path(d).is_dir():
            raise ConfigError(f"shards: no such directory {d!r}")
        found = sorted(Path(d).glob("shard-*.parquet"))
        if not found:
            raise ConfigError(f"shards: no shard-*.parquet files in {d!r}")
        files.extend(found)
    return files


def check_unique(files: list[Path]) -> None:
    """Two shards holding the same trajectory id (a folder given twice, or two runs numbered alike) would
    overwrite each other's grids and count twice: refuse before anything is written."""
    seen: dict[str, Path] = {}
    for f in files:
        for row in _rows([f], ["variant", "episode_id"]):
            traj = f"{row['variant']}-{row['episode_id']}"
            if traj in seen:
                raise ConfigError(
                    f"shards: trajectory {traj} is in both {seen[traj]} and {f} (a folder given twice, or two "
                    "generation runs numbered alike: give the second its own first_pair)"
                )
            seen[traj] = f


def check_rendered(cfg: DictConfig, max_frames: int) -> None:
    """Shards generated with `render_frames=M` hold the images of the keyframes an M-frame grid shows (the
    picks of a smaller grid are not always among them): refuse another grid size before anything is written."""
    for d in _shard_dirs(cfg):
        run = Path(d) / "run.json"
        rendered = json.loads(run.read_text()).get("render_frames") if run.is_file() else None
        if rendered is not None and rendered != max_frames:
            raise ConfigError(
                f"grid.max_frames: {d} was generated with render_frames={rendered} (images of the "
                f"keyframes a {rendered}-frame grid shows); build with grid.max_frames={rendered} "
                "or regenerate with render_frames=null"
            )


def _rows(files: list[Path], columns: list[str] = READ_COLUMNS):
    for f in files:
        try:
            pf = pq.ParquetFile(f)
            missing = [c for c in columns if c not in pf.schema_arrow.names]
            if missing:
                raise ConfigError(f"shards: {f} lacks columns {missing}")
            for batch in pf.iter_batches(batch_size=16, columns=columns):
                yield from batch.to_pylist()
        except ConfigError:
            raise
        except Exception as e:  # pyarrow raises several types for a corrupt file
            raise ConfigError(f"shards: cannot read {f} ({type(e).__name__}: {str(e).splitlines()[0]})") from None


def _pair_cut_frames(files: list[Path], max_frames: int) -> dict[str, int | None]:
    """variant-pair_id -> the earliest grid failure frame of the pair's twins (None if both succeeded), read from
    the label columns only (no images)."""
    frames: dict[str, int | None] = {}
    for row in _rows(files, ["variant", "pair_id", "success", "failure_keyframe", "keyframes"]):
        key, fr = f"{row['variant']}-{row['pair_id']}", grid_failure_frame(row, grid_picks(row, max_frames))
        old = frames.get(key)
        frames[key] = fr if old is None else old if fr is None else min(old, fr)
    return frames


def _review_marks(path: str | None) -> dict[str, str]:
    if path is None:
        return {}
    try:
        marks = json.loads(Path(path).read_text())["marks"]
        assert isinstance(marks, dict) and all(v in ("accept", "reject") for v in marks.values())
    except (OSError, ValueError, KeyError, TypeError, AssertionError):
        raise ConfigError(f"review: {path} is not a marks file exported by review.html") from None
    return marks


def _grid_config(cfg: DictConfig) -> GridConfig:
    """The grid settings, checked by GridConfig (a bad one is a one-line config error)."""
    try:
        return GridConfig(**OmegaConf.to_container(cfg.grid))  # type: ignore[arg-type]
    except (TypeError, ValueError) as e:
        raise ConfigError(str(e)) from None


def fractions(key: str, value: Any, n: int, whole: bool = True) -> tuple[float, ...]:
    """A ratios setting: `n` non-negative numbers summing to 1 (`whole`) or at most 1 (one-line ConfigError
    naming `key` otherwise)."""
    try:
        out = tuple(float(r) for r in value)
    except (TypeError, ValueError):
        out = ()
    total = sum(out)
    if len(out) != n or any(r < 0 for r in out) or (abs(total - 1) > 1e-6 if whole else total > 1 + 1e-6):
        raise ConfigError(f"{key}: {n} non-negative fractions summing to {'' if whole else 'at most '}1, got {value!r}")
    return out


def _check_ratios(cfg: DictConfig) -> None:
    """The seen train/val/test ratios: three non-negative fractions summing to 1."""
    fractions("ratios", cfg.ratios, 3)


def _prefix_questions(cfg: DictConfig) -> list[str]:
    """prefix.cuts, prefix.pair_cuts and prefix.questions checked; returns the prefix questions as a list."""
    require_ints(cfg.prefix, ("cuts",), 0, "prefix.")
    if not isinstance(cfg.prefix.pair_cuts, bool):
        raise ConfigError(f"prefix.pair_cuts: true or false, got {cfg.prefix.pair_cuts!r}")
    got = cfg.prefix.questions
    questions = list(got) if OmegaConf.is_list(got) else [got]
    if (
        questions[:2] != ["Q2", "Q3"]
        or not set(questions) <= set(PREFIX_QUESTIONS)
        or len(set(questions)) != len(questions)
    ):
        raise ConfigError(
            f"prefix.questions: Q2, Q3, then any of Q5, Q6 (Q4's severity is a rule on the final "
            f"state, which a prefix does not show), got {questions}"
        )
    return questions


def _views(cfg: DictConfig) -> list[str] | None:
    """The camera views of each grid, in order (None: every view of the shards)."""
    views = names(cfg.views)
    if views is not None and (not views or len(set(views)) != len(views)):
        raise ConfigError(f"views: expected distinct camera names, e.g. [front, side], got {views}")
    return views


def _paraphraser(cfg: DictConfig) -> Paraphraser | None:
    """The LLM rewording client when paraphrase.enabled, else None."""
    return (
        Paraphraser(
            cfg.paraphrase.base_url,
            cfg.paraphrase.model,
            cfg.paraphrase.api_key_env,
            cfg.paraphrase.timeout_s,
            int(cfg.seed),
        )
        if cfg.paraphrase.enabled
        else None
    )


def _out_dir(cfg: DictConfig) -> Path:
    """The output folder with its images/ and plots/ made."""
    return make_dir("out_dir", cfg.out_dir, "images", "plots")


def _check_variant(row: dict[str, Any]) -> None:
    """Refuse a row of a variant the dataset does not know (with a hint for shards of a renamed one)."""
    if row["variant"] not in DATA_VARIANTS:
        why = (
            " (shards made before each variant drew its own episodes replay the seen run's: regenerate them)"
            if row["variant"] in RENAMED_VARIANTS
            else ""
        )
        raise ConfigError(f"shards: row {row['episode_id']} has unknown variant {row['variant']!r}{why}")


def _paraphrase(ann: Annotated, para: Paraphraser, dimensions: Any, para_stats: Counter[str]) -> None:
    """Replace each record of `dimensions` (never Q2) by its rewording when that passes the filter."""
    for i, rec in enumerate(ann.records):
        dim = rec["id"].rsplit("_", 1)[-1]
        if dim not in dimensions or dim == "Q2":
            continue
        new = para.reword(rec, dim, ann.meta["task"])
        if new is not None and check_record(new, ann.meta) is None:
            ann.records[i] = new
            para_stats["accepted"] += 1
        else:
            para_stats["rejected"] += 1


def _write_grids(ann: Annotated, out: Path) -> None:
    """Write the trajectory's grid and its prefix grids as PNGs, then drop them from memory."""
    for a in (ann, *ann.prefixes):
        save_image(a.grid, out / a.image_name, optimize=False, compress_level=3)
        a.grid = None  # on disk now; held in memory, 17,000 grids of 512 x 512 px took 13 GB


@dataclasses.dataclass
class _Annotation:
    """The annotation pass's results: the kept trajectories and the counts that stats.json reports."""

    kept: list[Annotated] = dataclasses.field(default_factory=list)
    drops: Counter[str] = dataclasses.field(default_factory=Counter)
    para_stats: Counter[str] = dataclasses.field(default_factory=Counter)
    total_rows: int = 0


def _annotate_all(
    cfg: DictConfig,
    files: list[Path],
    gcfg: GridConfig,
    questions: list[str],
    views: list[str] | None,
    marks: dict[str, str],
    para: Paraphraser | None,
    out: Path,
) -> _Annotation:
    """Annotate every shard row, filter its records and write the grids of the trajectories kept."""
    rng = np.random.default_rng(int(cfg.seed))
    # Twins cut at the same keyframes: before their failure the two prefix grids are the same picture with the
    # same answer, after it they differ by the failure alone (a clean contrast for pair batches).
    pair_cuts = int(cfg.prefix.cuts) > 0 and cfg.prefix.pair_cuts
    cut_frames = _pair_cut_frames(files, gcfg.max_frames) if pair_cuts else {}
    res = _Annotation()
    n_total = sum(pq.ParquetFile(f).metadata.num_rows for f in files)
    for row in tqdm(_rows(files), total=n_total, desc="annotate", unit="traj", disable=not cfg.progress):
        res.total_rows += 1
        _check_variant(row)
        # prefix cuts draw from their own stream: the main records are the same with or without them
        group = f"{row['variant']}-{row['pair_id']}"
        traj_key = zlib.crc32((group if pair_cuts else f"{row['variant']}-{row['episode_id']}").encode())
        ann = annotate(
            row,
            gcfg,
            rng,
            int(cfg.prefix.cuts),
            np.random.default_rng([int(cfg.seed), traj_key]),
            int(cfg.aux.per_trajectory),
            cut_frames.get(group),
            prefix_questions=questions,
            views=views,
        )
        if marks.get(ann.trajectory) == "reject":
            res.drops["review_rejected"] += 1
            continue
        if para is not None:
            _paraphrase(ann, para, cfg.paraphrase.dimensions, res.para_stats)
        reasons = [r for a in (ann, *ann.prefixes) for rec in a.records if (r := check_record(rec, a.meta))]
        reasons += [r for rec in ann.aux if (r := check_record(rec, ann.meta))]
        if reasons:
            res.drops.update(reasons)
            continue
        _write_grids(ann, out)
        res.kept.append(ann)
    return res


def _split_records(kept: list[Annotated], cfg: DictConfig) -> dict[str, list[dict[str, Any]]]:
    """Assign each kept trajectory (and its prefixes) a split; split name -> its records."""
    split_of = assign([(a.group, a.variant) for a in kept], int(cfg.seed), tuple(cfg.ratios))
    splits: dict[str, list[dict[str, Any]]] = {s: [] for s in (*SEEN_SPLITS, *HELD_OUT_SPLITS, *REPLAY_SPLITS)}
    for a in kept:
        a.meta["split"] = split_of[a.group]
        splits[split_of[a.group]].extend(a.records)
        if a.meta["split"] == "train":  # facts are a training signal; the benchmark never asks them
            splits["train"].extend(a.aux)
        for p in a.prefixes:  # training prefixes train with the rest; evaluation ones are scored separately
            p.meta["split"] = split_of[a.group]
            name = "train" if p.meta["split"] == "train" else f"{p.meta['split']}_prefix"
            splits.setdefault(name, []).extend(p.records)
    return splits


def _write_splits(out: Path, splits: dict[str, list[dict[str, Any]]]) -> None:
    """Write each split's records (the seen splits always, others when not empty) and dataset_info.json."""
    for name, recs in splits.items():
        if name in SEEN_SPLITS or recs:
            atomic_write_json(out / f"{name}.json", recs)
    atomic_write_json(
        out / "dataset_info.json",
        {
            f"labrobfail_{name}": {
                "file_name": f"{name}.json",
                "formatting": "sharegpt",
                "columns": {"messages": "conversations", "images": "images"},
                "tags": {"role_tag": "from", "content_tag": "value", "user_tag": "human", "assistant_tag": "gpt"},
            }
            for name, recs in splits.items()
            if name in SEEN_SPLITS or recs
        },
    )


def build(cfg: DictConfig) -> dict[str, Any]:
    require_ints(cfg, ("seed", "review_sample"), 0)  # the review page is written last: its count is checked first
    files = _shard_files(cfg)
    check_unique(files)
    gcfg = _grid_config(cfg)
    check_rendered(cfg, gcfg.max_frames)
    _check_ratios(cfg)
    questions = _prefix_questions(cfg)
    views = _views(cfg)
    marks = _review_marks(cfg.review)
    para = _paraphraser(cfg)
    out = _out_dir(cfg)
    if para is not None:
        para.open_cache(out)

    res = _annotate_all(cfg, files, gcfg, questions, views, marks, para, out)
    kept = res.kept
    splits = _split_records(kept, cfg)
    _write_splits(out, splits)
    trajectories = [a.meta for a in kept]
    atomic_write_json(out / "trajectories.json", trajectories + [p.meta for a in kept for p in a.prefixes])
    dense = robot_baseline.dense_bytes([a.trajectory for a in kept], [a.dense for a in kept])
    atomic_write_bytes(out / robot_baseline.DENSE_FILE, dense)
    stats = dataset_stats(trajectories, splits, res.total_rows, res.drops, res.para_stats, gcfg)
    stats["prefix"] = {
        "cuts": int(cfg.prefix.cuts),
        "pair_cuts": bool(cfg.prefix.pair_cuts),
        "questions": questions,
        "grids": sum(len(a.prefixes) for a in kept),
    }
    stats["views"] = views  # the camera views in each grid, in order (null: every view of the shards)
    stats["drawing"] = drawing.merge([drawing.of_shards(d) for d in _shard_dirs(cfg)])  # lamp, glass
    stats["aux"] = {
        "per_trajectory": int(cfg.aux.per_trajectory),
        "records": sum(len(a.aux) for a in kept if a.meta["split"] == "train"),
    }
    atomic_write_json(out / "stats.json", stats)
    from labrobfail_data.plots import write_plots
    from labrobfail_data.review import write_review_page

    write_plots(trajectories, out / "plots")
    write_review_page(kept, out / "review.html", int(cfg.review_sample), int(cfg.seed))
    return stats


def dataset_stats(
    traj: list[dict[str, Any]],
    splits: dict[str, list],
    total_rows: int,
    drops: Counter,
    para: Counter,
    gcfg: GridConfig,
) -> dict[str, Any]:
    fails = [t for t in traj if not t["success"]]
    return {
        "trajectories_in": total_rows,
        "trajectories_kept": len(traj),
        "records": sum(len(r) for r in splits.values()),
        "filter": {
            "dropped_trajectories": total_rows - len(traj),
            "by_reason": dict(drops),
            "drop_rate": round((total_rows - len(traj)) / total_rows, 4) if total_rows else 0.0,
        },
        "paraphrase": dict(para),
        "splits": {
            k: {"records": len(v), "trajectories": len({Q.traj_of(r["id"]) for r in v})}
            for k, v in splits.items()
            if v or k in SEEN_SPLITS
        },
        "by_outcome": {"success": len(traj) - len(fails), "failure": len(fails)},
        "by_failure_type": dict(Counter(t["failure_type"] for t in fails).most_common()),
        "by_category": dict(sorted(Counter(str(t["category"]) for t in fails).items())),
        "by_severity": dict(sorted(Counter(str(t["severity"]) for t in fails).items())),
        "by_strategy": dict(Counter(t["strategy"] for t in fails).most_common()),
        "by_horizon": dict(Counter(t["horizon"] for t in traj)),
        "by_task": dict(sorted(Counter(t["scenario"] for t in traj).items())),
        "grid": dataclasses.asdict(gcfg),
    }
