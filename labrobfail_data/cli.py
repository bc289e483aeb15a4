"""The console scripts of the dataset step: `labrobfail-build-dataset` and `labrobfail-build-tower-data`.

Run as:
    labrobfail-build-dataset shards=outputs/demo_shards out_dir=outputs/demo_dataset
    labrobfail-build-dataset 'shards=[outputs/seen,outputs/val_both]' out_dir=outputs/dataset
    labrobfail-build-dataset shards=outputs/seen out_dir=outputs/dataset review=review_marks.json
    labrobfail-build-dataset shards=outputs/seen out_dir=outputs/ds_noidx grid.draw_index=false
    labrobfail-build-tower-data 'data.shards=[outputs/tower/shards/seen,outputs/tower/shards/val_object]' \
        data.out_dir=outputs/tower/data

build-dataset (defaults: configs/dataset.yaml) writes keyframe grids, six-dimension VQA records, train/val/test.json
(+ val_*.json, test_*.json), images/, stats.json (with the filter report), plots/ and review.html into out_dir.
build-tower-data (defaults: configs/tower.yaml's `data` section) writes the tower's per-frame targets:
frames-*.parquet and index.json (targets, splits, counts) into data.out_dir.
"""

from __future__ import annotations

import json

from labrobfail_vlm.config import cli_main, load_config


def build_dataset(argv: list[str]) -> int:
    from labrobfail_data.build import build

    stats = build(load_config("dataset.yaml", argv))
    print(json.dumps({k: stats[k] for k in ("trajectories_kept", "records", "filter", "splits", "by_outcome")}))
    return 0


def build_tower_data(argv: list[str]) -> int:
    from labrobfail_data.tower_data import build

    index = build(load_config("tower.yaml", argv).data)
    print(json.dumps({k: index[k] for k in ("trajectories", "failures", "shards")}))
    return 0


def build_dataset_cli() -> None:
    """The `labrobfail-build-dataset` console script."""
    cli_main(build_dataset, __doc__)


def build_tower_data_cli() -> None:
    """The `labrobfail-build-tower-data` console script."""
    cli_main(build_tower_data, __doc__)
