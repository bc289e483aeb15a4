"""Diagnose one failure trajectory of a dataset's test split and print it beside its ground truth (make demo).

Run as:
    python scripts/demo_diagnosis.py dataset=outputs/demo_dataset model=outputs/demo_train/final

The grid, the task text and the scene's object names come from the dataset; Q6 is chosen among the paper's
correction strategies with those names filled in (q6_mode="template"), so the correction is an instruction
that maps to robot primitives. The same call a robot stack makes: FailureAnalyzer.analyze(grid, task, objects).
"""

from __future__ import annotations

import json
from pathlib import Path

from labrobfail_vlm.config import ConfigError, cli_main, load_config

DEFAULTS = """
dataset: outputs/demo_dataset      # a dataset built by labrobfail-build-dataset (its test split)
model: outputs/demo_train/final    # the checkpoint that diagnoses
"""


def main(argv: list[str]) -> int:
    cfg = load_config(DEFAULTS, argv)
    ds, model = Path(str(cfg.dataset)), Path(str(cfg.model))
    meta = ds / "trajectories.json"
    if not meta.is_file():
        raise ConfigError(f"dataset: {meta} not found (build it with labrobfail-build-dataset)")
    traj = [t for t in json.loads(meta.read_text()) if t.get("split") == "test" and "prefix_of" not in t]
    fail = next((t for t in traj if not t["success"]), None)
    if fail is None:
        raise ConfigError(f"dataset: the test split of {ds} has no failure trajectory")
    from labrobfail_vlm.analyzer import FailureAnalyzer
    from labrobfail_vlm.images import load_image
    from labrobfail_vlm.taxonomy import Severity

    fa = FailureAnalyzer.from_pretrained(model, q6_mode="template")
    diag = fa.analyze(
        load_image(str(ds / "images" / f"{fail['trajectory']}.png")),
        task=fail["task"],
        objects=fail["objects"],
        frames=fail["frames"],
    )
    print(
        f"ground truth: {fail['trajectory']} ({fail['scenario']}): {fail['failure_type']} at frame {fail['frame']}, "
        f"severity {Severity(fail['severity']).display}, category {fail['category']}, strategy {fail['strategy']}"
    )
    print(diag.to_json())
    return 0


if __name__ == "__main__":
    cli_main(main, __doc__)
