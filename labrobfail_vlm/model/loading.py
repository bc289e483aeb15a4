"""Load Qwen3-VL and its processor from a local directory: safetensors only, no remote code, no hub.

A real checkpoint (e.g. Qwen3-VL-8B-Instruct downloaded elsewhere) and the tiny preset go
through this same function. A missing or incomplete directory is a one-line ConfigError.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from labrobfail_vlm.config import ConfigError


def check_model_dir(path: str | Path, field: str = "model.path", weights: bool = True) -> Path:
    p = Path(path)
    if not p.is_dir():
        raise ConfigError(f"{field}: no such model directory {str(path)!r}")
    if not ((p / "tokenizer.json").is_file() or (p / "tokenizer_config.json").is_file()):
        raise ConfigError(f"{field}: {path} has no tokenizer files")
    if not weights:
        return p
    if not (p / "config.json").is_file():
        raise ConfigError(f"{field}: {path} has no config.json (not a Hugging Face model directory)")
    if not list(p.glob("*.safetensors")) and not (p / "model.safetensors.index.json").is_file():
        bins = list(p.glob("*.bin")) + list(p.glob("*.pt"))
        raise ConfigError(f"{field}: {path} has no .safetensors weights" +
                          (" (pickle weights are refused)" if bins else ""))
    return p


def load_processor(path: str | Path):
    from labrobfail_vlm.model.processor import LabRobFailProcessor

    p = check_model_dir(path, weights=False)
    try:
        return LabRobFailProcessor.from_pretrained(str(p))
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ConfigError(f"model: cannot load the processor from {path} ({type(e).__name__})") from None


def load_model(path: str | Path, dtype: Any = None, **kwargs: Any):
    import torch
    from transformers import Qwen3VLForConditionalGeneration

    p = check_model_dir(path)
    try:
        return Qwen3VLForConditionalGeneration.from_pretrained(
            str(p), dtype=dtype or torch.float32, use_safetensors=True, trust_remote_code=False,
            local_files_only=True, **kwargs)
    except (OSError, ValueError, KeyError, RuntimeError) as e:
        raise ConfigError(f"model.path: cannot load {path} ({type(e).__name__}: {str(e).splitlines()[0][:200]})"
                          ) from None
