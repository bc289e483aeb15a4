"""Train an ACT policy on the backend's successful scripted demonstrations of a task family.

Run as:
    python scripts/train_act.py task=pick demos=50 out_dir=outputs/act/pick
    python scripts/train_act.py task=pour demos=50 train.max_minutes=45 out_dir=outputs/act/pour
    python scripts/train_act.py task=pick demos=4 train.steps=20 out_dir=/tmp/act   # a smoke run
    python scripts/train_act.py ... resume=true   # after a kill: on from the newest checkpoints/step-N

Writes out_dir/demos.npz (reused by a rerun with the same recording settings), out_dir/final/
(model.safetensors + act.json: the checkpoint labrobfail-supervise's policy=act and labrobfail-serve-policy load),
checkpoints/step-N and train_log.json (demos, steps, minutes, loss curve). Defaults: configs/act.yaml.
"""

from __future__ import annotations

import json

from labrobfail_vlm.config import cli_main, load_config


def main(argv: list[str]) -> int:
    from labrobfail_vlm.config import ConfigError, is_int
    from sim_backends.policies.act.data import MISS_MIN
    from sim_backends.policies.act.train import augment_config, train
    from sim_backends.registry import available_backends, make_backend
    from sim_backends.supervision.experiment import families, resolve_tasks, scenario_templates

    cfg = load_config("act.yaml", argv)
    for key in ("noise", "carry_noise", "miss"):  # metres: a negative or non-number draw is meaningless
        if not isinstance(cfg[key], (int, float)) or isinstance(cfg[key], bool) or cfg[key] < 0:
            raise ConfigError(f"{key}: metres >= 0, not {cfg[key]!r}")
    if not is_int(cfg.regrasp_demos, 0):
        raise ConfigError(f"regrasp_demos: a number of demonstrations >= 0, not {cfg.regrasp_demos!r}")
    if cfg.regrasp_demos and cfg.miss < MISS_MIN:  # a smaller miss records plain demos under regrasp seeds
        raise ConfigError(f"miss: regrasp demonstrations need a miss of at least {MISS_MIN} m, not {cfg.miss!r}")
    if cfg.train.schedule not in ("constant", "cosine"):
        raise ConfigError(f"train.schedule: expected constant or cosine, got {cfg.train.schedule!r}")
    if not is_int(cfg.train.warmup, 0):
        raise ConfigError(f"train.warmup: a number of steps >= 0, not {cfg.train.warmup!r}")
    if not isinstance(cfg.resume, bool):
        raise ConfigError(f"resume: true or false, not {cfg.resume!r}")
    augment_config(cfg.train.augment)  # a bad value fails here, not after the demonstrations are recorded
    if cfg.backend not in available_backends():
        raise ConfigError(f"backend: unknown backend {cfg.backend!r}; available: {', '.join(available_backends())}")
    src = make_backend(cfg.backend, render=False)  # only its scenario catalogue
    try:
        templates = scenario_templates(src)
    finally:
        src.close()
    tasks = resolve_tasks(str(cfg.task), families(load_config("supervise.yaml", []), templates), list(templates))
    if len(tasks) != 1:
        raise ConfigError("task: name one task family or scenario")
    summary = train(cfg, tasks[0])
    print(json.dumps({k: v for k, v in summary.items() if k != "curve"}))
    return 0


if __name__ == "__main__":
    cli_main(main, __doc__)
