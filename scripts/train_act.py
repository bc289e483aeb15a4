"""Train an ACT policy on the backend's successful scripted demonstrations of a task family.

Run as:
    python scripts/train_act.py task=pick demos=50 out_dir=outputs/act/pick
    python scripts/train_act.py task=pour demos=50 train.max_minutes=45 out_dir=outputs/act/pour
    python scripts/train_act.py task=pick demos=4 train.steps=20 out_dir=/tmp/act   # a smoke run

Writes out_dir/demos.npz (reused by a rerun with the same recording settings), out_dir/final/
(model.safetensors + act.json: the checkpoint scripts/supervise.py's policy=act and serve_policy.py load),
checkpoints/step-N and train_log.json (demos, steps, minutes, loss curve). Defaults: configs/act.yaml.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from labrobfail_vlm.config import cli_main, load_config  # noqa: E402


def main(argv: list[str]) -> int:
    from policies.act.train import train
    from sim_backends.registry import backend_spec
    from supervision.experiment import families, resolve_tasks

    cfg = load_config("act.yaml", argv)
    fams = families(load_config("supervise.yaml", []))
    tasks = resolve_tasks(str(cfg.task), fams, backend_spec(cfg.backend).cls.list_scenarios())
    if len(tasks) != 1:
        from labrobfail_vlm.config import ConfigError
        raise ConfigError("task: name one task family or scenario")
    summary = train(cfg, tasks[0])
    print(json.dumps({k: v for k, v in summary.items() if k != "curve"}))
    return 0


if __name__ == "__main__":
    cli_main(main)
