"""Build LabRobFail-Data from simulator shards: keyframe grids, six-dimension VQA records, splits, stats, plots.

Run as:
    python scripts/build_dataset.py shards=outputs/demo_shards out_dir=outputs/demo_dataset
    python -m scripts.build_dataset shards=outputs/demo_shards out_dir=outputs/demo_dataset
    python -m scripts.build_dataset 'shards=[outputs/seen,outputs/val_both]' out_dir=outputs/dataset
    python -m scripts.build_dataset shards=outputs/seen out_dir=outputs/dataset review=review_marks.json
    python -m scripts.build_dataset shards=outputs/seen out_dir=outputs/ds_noidx grid.draw_index=false

Defaults: configs/dataset.yaml. Writes train/val/test.json (+ val_*.json, test_*.json), images/,
stats.json (with the filter report), plots/ and review.html into out_dir.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

# data/ is the checkout's tooling, not an installed package: `python scripts/build_dataset.py` finds it here
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data.build import build  # noqa: E402
from labrobfail_vlm.config import cli_main, load_config  # noqa: E402


def main(argv: list[str]) -> int:
    stats = build(load_config("dataset.yaml", argv))
    print(json.dumps({k: stats[k] for k in ("trajectories_kept", "records", "filter", "splits", "by_outcome")}))
    return 0


if __name__ == "__main__":
    cli_main(main, __doc__)
