"""HybridTrainer: transformers' Trainer with one AdamW over per-group learning rates and LabRobFail checkpoints."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from transformers import Trainer

from labrobfail_vlm.model.hybrid import param_groups
from labrobfail_vlm.train.checkpoint import save_trainable


class HybridTrainer(Trainer):
    def __init__(self, *args: Any, group_lrs: dict[str, float], base_model: str, tuning: str, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.group_lrs, self.base_model, self.tuning = group_lrs, base_model, tuning

    def create_optimizer(self, model=None):  # noqa: D102 - one optimizer, a learning rate per parameter group
        if self.optimizer is None:
            groups = param_groups(model or self.model, self.group_lrs, self.args.weight_decay)
            self.optimizer = torch.optim.AdamW(groups, betas=(self.args.adam_beta1, self.args.adam_beta2),
                                               eps=self.args.adam_epsilon)
        return self.optimizer

    def _save(self, output_dir: str | None = None, state_dict: dict | None = None) -> None:
        # Under ZeRO-3 `save_model` gathers `state_dict` collectively on every rank before calling this.
        if not self.args.should_save:
            return
        out = Path(output_dir or self.args.output_dir)
        model = self.accelerator.unwrap_model(self.model)
        save_trainable(model, out, model.state_dict() if state_dict is None else state_dict, self.base_model,
                       self.tuning)
        if self.processing_class is not None:
            self.processing_class.save_pretrained(out)
