"""Hybrid fine-tuning (paper: Architecture and Hybrid Fine-tuning): which parameters train, at which rate.

Tuning modes
  hybrid         vision encoder + merger fully trained, LoRA on the text decoder's linear layers (the paper)
  full           every parameter trained (ablation "full fine-tuning")
  frozen_vision  encoder and merger frozen, LoRA on the decoder only (ablation)
Parameter groups, each with its own learning rate in one optimizer:
  vision  model.visual.* except the mergers
  merger  model.visual.merger.*, model.visual.deepstack_merger_list.*
  lora    lora_A / lora_B of the text decoder
  text    the rest of the language model and lm_head (full mode only)
"""

from __future__ import annotations

import re
from typing import Any

import torch

LORA_TARGETS = r".*language_model\.layers\.\d+\.(self_attn\.(q|k|v|o)_proj|mlp\.(gate|up|down)_proj)"
MODES = ("hybrid", "full", "frozen_vision")
GROUPS = ("vision", "merger", "lora", "text")
_MERGER = re.compile(r"\.visual\.(merger|deepstack_merger_list)\.")
_VISUAL = re.compile(r"(^|\.)visual\.")


def group_of(name: str) -> str:
    if "lora_" in name:
        return "lora"
    if _MERGER.search(name) or name.startswith(("visual.merger.", "visual.deepstack_merger_list.")):
        return "merger"
    if _VISUAL.search(name):
        return "vision"
    return "text"


def apply_tuning(model: torch.nn.Module, mode: str, lora: dict[str, Any]) -> torch.nn.Module:
    """Return the model to train (a PeftModel unless mode == 'full') with requires_grad set per mode."""
    if mode not in MODES:
        raise ValueError(f"tuning: expected one of {', '.join(MODES)}, got {mode!r}")
    if mode == "full":
        model.requires_grad_(True)
        return model
    from peft import LoraConfig, get_peft_model

    cfg = LoraConfig(
        r=int(lora["r"]),
        lora_alpha=int(lora["alpha"]),
        lora_dropout=float(lora["dropout"]),
        target_modules=LORA_TARGETS,
        bias="none",
    )
    peft_model = get_peft_model(model, cfg)
    for name, p in peft_model.named_parameters():
        g = group_of(name)
        p.requires_grad_(g == "lora" or (mode == "hybrid" and g in ("vision", "merger")))
    return peft_model


def freeze_zero_lr(model: torch.nn.Module, lrs: dict[str, float]) -> None:
    """A group whose learning rate is 0 is frozen outright (no gradients computed): `lr.vision=0 lr.merger=0`
    keeps a pretrained tower as it is while the rest trains."""
    for name, p in model.named_parameters():
        if p.requires_grad and float(lrs.get(group_of(name), 1.0)) == 0.0:
            p.requires_grad_(False)


def param_groups(model: torch.nn.Module, lrs: dict[str, float], weight_decay: float = 0.0) -> list[dict[str, Any]]:
    groups: dict[str, list[torch.nn.Parameter]] = {g: [] for g in GROUPS}
    for name, p in model.named_parameters():
        if p.requires_grad:
            groups[group_of(name)].append(p)
    return [
        {"params": ps, "lr": float(lrs[g]), "weight_decay": weight_decay, "name": g} for g, ps in groups.items() if ps
    ]


def count_trainable(model: torch.nn.Module) -> dict[str, int]:
    out = {g: 0 for g in GROUPS}
    frozen = 0
    for name, p in model.named_parameters():
        n = p.ds_numel if hasattr(p, "ds_numel") else p.numel()  # ZeRO-3 partitions hold a 0-size tensor
        if p.requires_grad:
            out[group_of(name)] += n
        else:
            frozen += n
    return {**out, "frozen": frozen}
