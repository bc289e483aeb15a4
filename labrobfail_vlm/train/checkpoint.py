"""Fine-tuned checkpoints: LoRA adapter (peft) + fully trained vision/merger weights + a small manifest.

Layout of a checkpoint directory:
  adapter_config.json, adapter_model.safetensors   the decoder's LoRA (peft format)
  vision_merger.safetensors                        model.visual.* weights (hybrid mode)
  model.safetensors + config.json                  full weights instead (full mode)
  labrobfail.json                                  {"base_model": DIR, "tuning": mode, "grid": {...}}
  processor files                                  tokenizer, chat template, image processor
`load_finetuned` rebuilds the model from the base directory; scripts/merge.py writes a standalone model.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file

from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.grid import GridConfig
from labrobfail_vlm.io import atomic_write_json
from labrobfail_vlm.model.hybrid import group_of

MANIFEST = "labrobfail.json"
VISION_FILE = "vision_merger.safetensors"
_PEFT_PREFIX = "base_model.model."


def save_trainable(model: Any, out: Path, state_dict: dict[str, torch.Tensor], base_model: str, tuning: str,
                   grid: dict[str, Any] | None = None) -> None:
    """Write adapter + vision/merger (or full) weights from a state dict gathered on every rank.

    `grid` is the dataset's grid config; inference builds its grids (and bounds Q3) the same way.
    """
    out.mkdir(parents=True, exist_ok=True)
    # Full model: every weight. PeftModel: it keeps only the lora_ keys of the state dict.
    model.save_pretrained(out, state_dict=state_dict, safe_serialization=True)
    if tuning == "hybrid":  # the fully trained vision encoder and merger, under the base model's names
        vis = {k.removeprefix(_PEFT_PREFIX): v.detach().cpu().contiguous() for k, v in state_dict.items()
               if group_of(k) in ("vision", "merger")}
        save_file(vis, str(out / VISION_FILE), metadata={"format": "pt"})
    atomic_write_json(out / MANIFEST, {"base_model": str(base_model), "tuning": tuning, "grid": grid})


def is_finetuned(path: str | Path) -> bool:
    return (Path(path) / MANIFEST).is_file()


def trained_grid(path: str | Path) -> GridConfig | None:
    """The grid config a checkpoint was trained on (None for a base model or an older checkpoint)."""
    try:
        grid = json.loads((Path(path) / MANIFEST).read_text()).get("grid")
    except (OSError, ValueError, AttributeError):
        return None
    if not isinstance(grid, dict):
        return None
    return GridConfig.from_dict(grid)


def load_finetuned(path: str | Path, dtype: Any = None):
    """Base model + adapter + vision weights, ready for inference (LoRA not merged)."""
    from labrobfail_vlm.model.loading import load_model

    p = Path(path)
    try:
        man = json.loads((p / MANIFEST).read_text())
    except (OSError, ValueError):
        raise ConfigError(f"model: {path} has no readable {MANIFEST}") from None
    if man["tuning"] == "full":
        return load_model(p, dtype)
    from peft import PeftModel

    base = load_model(man["base_model"], dtype)
    if man["tuning"] == "hybrid":
        if not (p / VISION_FILE).is_file():
            raise ConfigError(f"model: {path} lacks {VISION_FILE}")
        missing, unexpected = base.load_state_dict(load_file(str(p / VISION_FILE)), strict=False)
        if unexpected:
            raise ConfigError(f"model: {VISION_FILE} has unknown weights, e.g. {unexpected[0]}")
    if not (p / "adapter_model.safetensors").is_file():
        raise ConfigError(f"model: {path} lacks adapter_model.safetensors")
    return PeftModel.from_pretrained(base, str(p), is_trainable=False)
