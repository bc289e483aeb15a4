"""Build the vision tower's pretraining data: simulator shards -> frames and dense per-frame targets.

Run as:
    python -m scripts.build_tower_data 'data.shards=[outputs/tower/shards/seen,outputs/tower/shards/val_object]'
    python scripts/build_tower_data.py 'data.shards=[outputs/tower/shards/seen]' data.out_dir=outputs/tower/data

Defaults: configs/tower.yaml (section `data`). Resumable: a rerun skips the source shards already converted.
Writes frames-*.parquet and index.json (targets, splits, counts) into data.out_dir (data/tower_data.py).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

# data/ is the checkout's tooling, not an installed package: `python scripts/build_tower_data.py` finds it here
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data.tower_data import build  # noqa: E402
from labrobfail_vlm.config import cli_main, load_config  # noqa: E402


def main(argv: list[str]) -> int:
    cfg = load_config("tower.yaml", argv)
    index = build(cfg.data)
    print(json.dumps({k: index[k] for k in ("trajectories", "failures", "shards")}))
    return 0


if __name__ == "__main__":
    cli_main(main, __doc__)
