"""ACT checkpoints: `model.safetensors` (weights) + `act.json` (ACTConfig with the demos' statistics).

A training checkpoint (checkpoints/step-N) also holds what a resumed run needs to go on as if never stopped:
`optim.pt` (optimizer, schedule, torch RNG, the data order's generator at the start of the epoch; plain tensors,
read back with weights_only=True) and `train_state.json` (written last: a checkpoint without it is incomplete).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sim_backends.policies.act.configuration_act import ACTConfig

WEIGHTS, CONFIG = "model.safetensors", "act.json"
TRAIN_STATE = "train_state.json"  # written last into checkpoints/step-N, beside labrobfail_vlm.io's optim.pt


def save_checkpoint(model: Any, cfg: ACTConfig, out: str | Path) -> Path:
    from safetensors.torch import save

    from labrobfail_vlm.io import atomic_write_bytes

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out / WEIGHTS, save({k: v.detach().contiguous().cpu() for k, v in model.state_dict().items()}))
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


def save_progress(model: Any, cfg: ACTConfig, out: Path, tensors: dict[str, Any], state: dict[str, Any]) -> None:
    """A training checkpoint: the weights and config, `tensors` (optim.pt), then `state` (train_state.json)."""
    from labrobfail_vlm.io import RESUME_TENSORS, save_resume_state

    save_checkpoint(model, cfg, out)
    save_resume_state(out, tensors, state, TRAIN_STATE)
    for old in out.parent.glob("step-*"):  # earlier steps stay policy checkpoints; only the newest resumes
        if old != out:
            for f in (TRAIN_STATE, RESUME_TENSORS):
                (old / f).unlink(missing_ok=True)


def last_progress(root: Path) -> Path | None:
    """The newest complete training checkpoint under `root` (checkpoints/), or None."""
    from labrobfail_vlm.io import newest_complete

    return newest_complete(root, "step", TRAIN_STATE)


def load_progress(model: Any, path: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """Loads a training checkpoint's weights into `model`; returns its tensors (optim.pt) and state."""
    from safetensors.torch import load_file

    from labrobfail_vlm.io import load_resume_state

    model.load_state_dict(load_file(str(path / WEIGHTS)))
    return load_resume_state(path, TRAIN_STATE)
