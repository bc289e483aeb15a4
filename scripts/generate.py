"""Generate labeled failure/success episode pairs into Parquet shards.

Run as:
    python scripts/generate.py backend=pybullet num_episodes=200 out_dir=outputs/shards seed=0 workers=2
    python scripts/generate.py num_episodes=100 out_dir=outputs/unseen variant=unseen_both
    python scripts/generate.py num_episodes=1000 out_dir=outputs/big executor=ray workers=8

Rerunning the same command after a kill resumes; DIR/manifest.json summarises the run.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data.generate import generate, load_config  # noqa: E402
from labrobfail_vlm.config import cli_main  # noqa: E402


def main(argv: list[str]) -> int:
    man = generate(load_config(argv))
    print(json.dumps({k: man[k] for k in ("episodes", "by_outcome", "by_failure_type", "by_action", "by_horizon")}))
    return 0


if __name__ == "__main__":
    cli_main(main)
