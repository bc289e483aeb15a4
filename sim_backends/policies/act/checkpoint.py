"""ACT checkpoints: `model.safetensors` (weights) + `act.json` (ACTConfig with the demos' statistics)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from sim_backends.policies.act.configuration_act import ACTConfig

WEIGHTS, CONFIG = "model.safetensors", "act.json"


def save_checkpoint(model: Any, cfg: ACTConfig, out: str | Path) -> Path:
    from safetensors.torch import save_file

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / (WEIGHTS + ".tmp")
    save_file({k: v.detach().contiguous().cpu() for k, v in model.state_dict().items()}, str(tmp))
    os.replace(tmp, out / WEIGHTS)
    cfg.save(out / CONFIG)
    return out


def load_checkpoint(path: str | Path, device: str = "cpu", key: str = "act.checkpoint") -> tuple[Any, ACTConfig]:
    """The model (eval mode) and its config; ValueError "<key>: ..." for a missing or broken checkpoint."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    from sim_backends.policies.act.modeling_act import ACTModel

    p = Path(path) if path else None
    if p is None or not p.is_dir():
        raise ValueError(f"{key}: no checkpoint directory {str(path)!r} (train one with scripts/train_act.py)")
    for f in (WEIGHTS, CONFIG):
        if not (p / f).is_file():
            raise ValueError(f"{key}: {p} has no {f}")
    try:
        cfg = ACTConfig.load(p / CONFIG)
        model = ACTModel(cfg)
        model.load_state_dict(load_file(str(p / WEIGHTS)))
    except (ValueError, TypeError, RuntimeError, SafetensorError, OSError) as e:
        raise ValueError(f"{key}: cannot load {p} ({str(e).splitlines()[0][:120]})") from None
    if not cfg.stats:
        raise ValueError(f"{key}: {p / CONFIG} has no normalisation statistics")
    return model.to(device).eval(), cfg
