"""HybridTrainer: transformers' Trainer with one AdamW over per-group learning rates and LabRobFail checkpoints.

Loss: `token` is the causal-LM mean over every answer token in the batch (transformers' default). `record`
averages each record's answer tokens first, then takes the weighted mean over records. The closed-set
answers (Yes/No, a digit) are one token while a Q6 correction is ~30, so under `token` the detection and
classification questions get a few percent of the gradient; `record` gives each question its weight.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from transformers import Trainer, TrainerCallback

from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.model.hybrid import param_groups
from labrobfail_vlm.train.checkpoint import save_trainable
from labrobfail_vlm.train.curriculum import PairSampler
from labrobfail_vlm.train.data import IGNORE
from labrobfail_vlm.train.packing import prepare_packed

LOSS_MODES = ("token", "record")


def check_loss_mode(mode: str) -> str:
    if mode not in LOSS_MODES:
        raise ConfigError(f"loss.mode: expected one of {', '.join(LOSS_MODES)}, got {mode!r}")
    return mode


class HybridTrainer(Trainer):
    def __init__(
        self,
        *args: Any,
        group_lrs: dict[str, float],
        base_model: str,
        tuning: str,
        loss_mode: str = "token",
        grid: dict[str, Any] | None = None,
        drawing: dict[str, Any] | None = None,
        pair_batches: bool = False,
        grounding: dict[str, Any] | None = None,
        settings: dict[str, Any] | None = None,
        **kwargs: Any,
    ):
        super().__init__(*args, **kwargs)
        # grounding: {"head": make_head(...), "weight": float, "rank": float, "lr": float} (train/grounding.py)
        self.grounding = grounding
        self.tap = None
        self._grounding_log: float | None = None  # the last grounding loss, added to the logged losses
        if grounding is not None:
            from labrobfail_vlm.train.grounding import TokenTap

            self.tap = TokenTap(self.model)
            grounding["head"].to(self.args.device)
        self.group_lrs, self.base_model, self.tuning = group_lrs, base_model, tuning
        self.pair_batches = pair_batches
        self.loss_mode = check_loss_mode(loss_mode)
        self.grid, self.drawing = grid, drawing
        self.settings = settings  # the run's settings, recorded in each checkpoint for resume's check (train/resume.py)
        if loss_mode == "record":
            self.loss_is_scaled_for_ga = False  # a mean over this micro-batch's records: Trainer divides by GA

    def compute_loss(self, model, inputs, return_outputs=False, num_items_in_batch=None):  # noqa: D102
        weights = inputs.pop("record_weight", None)
        slots = inputs.pop("label_slot", None)
        targets, groups = inputs.pop("frame_target", None), inputs.pop("pair_group", None)
        thw = inputs.get("image_grid_thw")
        keys = inputs.pop("grid_keys", None)  # file keys of the grids (Collator with a tower cache)
        if keys is not None:
            self.data_collator.tower_cache.given = keys
        if "segment_ids" in inputs:  # shared-prefix packed rows (labrobfail_vlm/train/packing.py)
            inputs = prepare_packed(model, inputs)
        if self.loss_mode == "token":
            loss, outputs = super().compute_loss(model, inputs, True, num_items_in_batch)
        else:
            loss, outputs = record_loss(model, inputs, inputs.pop("labels"), weights, slots)
        if self.grounding is not None and targets is not None and model.training:
            from labrobfail_vlm.train.grounding import grounding_loss

            g = grounding_loss(
                self.grounding["head"], self.tap.take(), thw, targets, groups, float(self.grounding["rank"])
            )
            self._grounding_log = float(g.detach())
            loss = loss + float(self.grounding["weight"]) * g
        return (loss, outputs) if return_outputs else loss

    def log(self, logs: dict[str, float], *args: Any, **kwargs: Any) -> None:  # noqa: D102
        if self._grounding_log is not None and "loss" in logs:
            logs["grounding_loss"] = round(self._grounding_log, 4)
        super().log(logs, *args, **kwargs)

    def _get_train_sampler(self, train_dataset=None):  # noqa: D102 - curriculum: twins in one micro-batch
        ds = train_dataset if train_dataset is not None else self.train_dataset
        if not self.pair_batches:
            return super()._get_train_sampler(train_dataset)
        ids = ds.ids() if hasattr(ds, "ids") else [r["id"] for r in ds.records]
        return PairSampler(ids, ds.group_of, self.args.per_device_train_batch_size, self.args.seed)

    def create_optimizer(self, model=None):  # noqa: D102 - one optimizer, a learning rate per parameter group
        if self.optimizer is None:
            groups = param_groups(model or self.model, self.group_lrs, self.args.weight_decay)
            if self.grounding is not None:
                groups.append(
                    {
                        "params": list(self.grounding["head"].parameters()),
                        "lr": float(self.grounding["lr"]),
                        "weight_decay": self.args.weight_decay,
                        "name": "grounding",
                    }
                )
            self.optimizer = torch.optim.AdamW(
                groups, betas=(self.args.adam_beta1, self.args.adam_beta2), eps=self.args.adam_epsilon
            )
        return self.optimizer

    def _save(self, output_dir: str | None = None, state_dict: dict | None = None) -> None:
        # Under ZeRO-3 `save_model` gathers `state_dict` collectively on every rank before calling this.
        if not self.args.should_save:
            return
        out = Path(output_dir or self.args.output_dir)
        model = self.accelerator.unwrap_model(self.model)
        save_trainable(
            model,
            out,
            model.state_dict() if state_dict is None else state_dict,
            self.base_model,
            self.tuning,
            self.grid,
            self.drawing,
        )
        if self.processing_class is not None:
            self.processing_class.save_pretrained(out)
        if self.settings is not None:
            from labrobfail_vlm.io import atomic_write_json
            from labrobfail_vlm.train.resume import SETTINGS_FILE

            atomic_write_json(out / SETTINGS_FILE, self.settings)
        if self.grounding is not None:  # for resuming only; inference never reads it
            from labrobfail_vlm.train.grounding import save_head

            save_head(self.grounding["head"], out)


def record_loss(
    model: Any,
    inputs: dict[str, Any],
    labels: torch.Tensor,
    weights: torch.Tensor | None = None,
    slots: torch.Tensor | None = None,
) -> tuple[torch.Tensor, Any]:
    """Weighted mean over records of each record's mean answer-token cross-entropy.

    A record is a row, or with packed rows the `slots` id of its label tokens. Logits are computed only where
    the next token is a label (`logits_to_keep` as a boolean mask), so the vocabulary projection never runs
    over the image and prompt positions.
    """
    target = labels[:, 1:]
    keep = torch.zeros_like(labels, dtype=torch.bool)
    keep[:, :-1] = target != IGNORE
    outputs = model(**inputs, logits_to_keep=keep)
    tok = F.cross_entropy(
        outputs.logits.float().reshape(-1, outputs.logits.shape[-1]), target[target != IGNORE], reduction="none"
    )
    if slots is None:
        rows, n = keep.nonzero()[:, 0], labels.shape[0]
    else:
        rows = slots[:, 1:][target != IGNORE].to(tok.device)
        n = int(weights.numel()) if weights is not None else int(rows.max()) + 1
    per = torch.zeros(n, device=tok.device, dtype=tok.dtype).scatter_add_(0, rows, tok)
    per = per / torch.bincount(rows, minlength=n).clamp(min=1).to(per.dtype)
    w = torch.ones_like(per) if weights is None else weights.to(per.device, per.dtype)
    return (w * per).sum() / n, outputs


class ProgressLog(TrainerCallback):
    """At every checkpoint: optimizer step, training examples seen (records), wall and CPU seconds so far, into
    output_dir/progress.json; scripts/learning_curve.py turns the checkpoints into accuracy curves."""

    def __init__(self, out: Path, records_per_item: float = 1.0):
        self.out, self.per_item = Path(out), float(records_per_item)
        self.rows: list[dict[str, float]] = []
        self.t0 = self.c0 = 0.0
        self.before = (0.0, 0.0)  # wall and CPU seconds spent before train() (grounding pre-training)

    def start_after(self, wall_s: float, cpu_s: float) -> None:
        """Count `wall_s`/`cpu_s` already spent in this run (stage A) in every row's clocks."""
        self.before = (float(wall_s), float(cpu_s))

    def on_train_begin(self, args, state, control, **kwargs):  # noqa: D102
        from labrobfail_vlm.io import atomic_write_json

        self.t0, self.c0 = time.perf_counter() - self.before[0], time.process_time() - self.before[1]
        if not state.is_world_process_zero:  # one writer: ranks would race on the same file
            return
        self.out.mkdir(parents=True, exist_ok=True)
        path = self.out / "progress.json"
        self.rows = [
            r for r in (json.loads(path.read_text()) if path.is_file() else []) if r["step"] <= state.global_step
        ]  # a resumed run keeps the rows up to its checkpoint
        if self.rows:  # continue the clocks where the checkpoint left them
            self.t0 -= self.rows[-1]["wall_s"]
            self.c0 -= self.rows[-1]["cpu_s"]
        atomic_write_json(path, self.rows)

    def on_save(self, args, state, control, **kwargs):  # noqa: D102
        from labrobfail_vlm.io import atomic_write_json

        if not state.is_world_process_zero:
            return
        items = (
            state.global_step * args.per_device_train_batch_size * args.gradient_accumulation_steps * args.world_size
        )
        self.rows.append(
            {
                "step": state.global_step,
                "examples": round(items * self.per_item),
                "wall_s": round(time.perf_counter() - self.t0, 1),
                "cpu_s": round(time.process_time() - self.c0, 1),
            }
        )
        atomic_write_json(self.out / "progress.json", self.rows)
