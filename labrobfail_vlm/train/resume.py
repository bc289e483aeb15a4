"""Resuming a training run (labrobfail-train resume=...): which checkpoint, and that it can be read and loaded safely.

A checkpoint is refused in one line before the Trainer or DeepSpeed touches it when its weights or optimizer state
cannot be read (a disk that filled while saving), when DeepSpeed's own state files name objects beyond its plain state
(DeepSpeed unpickles them in full), when it lacks the grounding head the run trains with, or when it was trained with
other settings than the run resuming it (each checkpoint records them, SETTINGS_FILE).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from labrobfail_vlm.config import ConfigError, refuse_other_settings, settings_record

# What decides the trained weights is every setting but these: where and how often a run saves and reports, the
# frozen tower's cache (the same features either way), and its length: more steps or epochs extend a run, as the
# tower's pretraining allows, and from the resume on the cosine schedule and any curriculum phase set as a share of
# the run (curriculum.detect_first, polarity_warmup) are the longer run's. Anything else makes another run.
RESUME_FREE = (
    "resume",
    "progress",
    "output_dir",
    "save_steps",
    "save_total_limit",
    "logging_steps",
    "wandb",
    "tower_cache_mb",
    "epochs",
    "max_steps",
)
CATALOGUES = ("presets", "tiny_towers")  # every preset's settings: the chosen one is merged into the run's already
SETTINGS_FILE = "train_settings.json"


def run_settings(cfg: Any) -> dict[str, Any]:
    """The settings record (config.settings_record) less RESUME_FREE and CATALOGUES, as each checkpoint holds it
    (SETTINGS_FILE). Settings made from output_dir (preset tiny's model is built inside it) are resolved against a
    placeholder, so a run's folder copied elsewhere resumes."""
    from omegaconf import OmegaConf

    conf = OmegaConf.merge(cfg, {"output_dir": "<output_dir>"} if "output_dir" in cfg else {})
    out = settings_record(conf, (k for k in (*RESUME_FREE, *CATALOGUES) if k != "output_dir"))
    out.pop("output_dir", None)
    return out


def check_resume_settings(cfg: Any) -> None:
    """Before the model is built: the checkpoint `resume` names (or, for resume=true, the newest complete one, else a
    killed stage A's state) was trained with this run's settings. Nothing to resume is resume_point's to say."""
    from labrobfail_vlm.train.checkpoint import last_complete_checkpoint
    from labrobfail_vlm.train.grounding import STAGE_A_DIR, stage_a_state

    if cfg.resume is True:
        last, _ = last_complete_checkpoint(cfg.output_dir)
        if last is None and stage_a_state(cfg.output_dir) is not None:
            last = Path(cfg.output_dir) / STAGE_A_DIR
    elif isinstance(cfg.resume, str) and Path(cfg.resume).is_dir():
        last = Path(cfg.resume)
    else:
        return
    if last is not None:
        check_same_settings(last, run_settings(cfg))


def check_same_settings(ckpt: Path, settings: dict[str, Any]) -> None:
    """A checkpoint trained with other settings (a learning rate, the data's folders, the augmentation) is refused in
    one line naming the first that differs and both values: continuing it would make a model no single run makes. A
    checkpoint written before checkpoints recorded their settings is taken as it is."""
    f = ckpt / SETTINGS_FILE
    if not f.is_file():
        return
    try:
        recorded = json.loads(f.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        recorded = None
    if not isinstance(recorded, dict):
        raise ConfigError(f"resume: {f} is not a readable settings record (delete {ckpt}: the one before resumes)")
    refuse_other_settings(
        recorded, settings, (*RESUME_FREE, *CATALOGUES), ckpt, str(f), "output_dir", "labrobfail-train"
    )


def resume_point(cfg: Any, pre_epochs: int, dtype: Any) -> tuple[str | None, bool]:
    """(checkpoint to resume from or None, whether to resume stage A) for resume=true, a checkpoint path, or off;
    the checkpoint is checked readable (at the run's `dtype`) before anything loads it (its settings were checked
    before the model was built: check_resume_settings)."""
    from labrobfail_vlm.train.checkpoint import last_complete_checkpoint

    resume = None
    resume_stage_a = False
    if cfg.resume is True:
        from labrobfail_vlm.train.grounding import stage_a_state

        last, partial = last_complete_checkpoint(cfg.output_dir)
        for d in partial:  # a kill while saving: the run resumes from the checkpoint before it
            print(f"resume: skipping {d} (incompletely written)", file=sys.stderr, flush=True)
        if last is not None:
            resume = str(last)
        elif pre_epochs and stage_a_state(cfg.output_dir) is not None:  # killed in stage A (or before checkpoint-1)
            resume_stage_a = True
        else:
            raise ConfigError(f"resume: no complete checkpoint-N in {cfg.output_dir}")
    elif isinstance(cfg.resume, str):
        if not Path(cfg.resume).is_dir():
            raise ConfigError(f"resume: no such checkpoint {cfg.resume!r}")
        resume = cfg.resume
    if resume is not None:
        check_resumable(Path(resume), dtype)
    return resume, resume_stage_a


def check_resumable(ckpt: Path, dtype: Any) -> None:
    """A checkpoint whose weights or optimizer state cannot be read is one line here, not the trainer's traceback
    half-way through loading (a disk that filled while saving leaves such a folder with a complete-looking state)."""
    import zipfile

    from labrobfail_vlm.model.loading import safetensors_header
    from labrobfail_vlm.train.checkpoint import validate_checkpoint

    validate_checkpoint(ckpt, "resume", dtype=dtype)  # priced as the run loads it, as a fresh start is
    for f in sorted(ckpt.glob("*.safetensors")):  # the grounding head's too, which the model check does not read
        safetensors_header(f, "resume")
    opt = ckpt / "optimizer.pt"  # torch.save writes a zip archive
    if opt.exists() and not zipfile.is_zipfile(opt):
        raise ConfigError(f"resume: {opt} is not a readable optimizer state (delete {ckpt}: the one before resumes)")
    for f in sorted(ckpt.glob("global_step*/*.pt")):
        _check_deepspeed_state(f)


# What DeepSpeed's own states hold beyond tensors and plain containers (ZeRO-3 on these machines: the stage enum and
# the loss scaler); anything else in such a file is refused before DeepSpeed's loader unpickles it in full.
DEEPSPEED_GLOBALS = frozenset(
    {
        "deepspeed.runtime.zero.config.ZeroStageEnum",
        "deepspeed.runtime.fp16.loss_scaler.LossScaler",
        "deepspeed.runtime.fp16.loss_scaler.DynamicLossScaler",
    }
)


def _check_deepspeed_state(f: Path) -> None:
    """A DeepSpeed state file of a checkpoint to resume: DeepSpeed loads it with torch.load(weights_only=False), which
    runs whatever a pickle names, so its globals are read first (without unpickling) and any beyond plain state and
    DEEPSPEED_GLOBALS is one line: a checkpoint from elsewhere never runs code here."""
    import pickle

    import torch

    try:
        found = set(torch.serialization.get_unsafe_globals_in_checkpoint(f))
    except (OSError, RuntimeError, ValueError, EOFError, pickle.UnpicklingError) as e:
        raise ConfigError(f"resume: {f} is not a readable DeepSpeed state ({type(e).__name__})") from None
    if found - DEEPSPEED_GLOBALS:
        names = ", ".join(sorted(found - DEEPSPEED_GLOBALS))
        raise ConfigError(f"resume: {f} holds objects beyond DeepSpeed's plain state ({names}); not loaded")


def load_resumed_head(resume: str | None, grounding: dict[str, Any] | None) -> None:
    """Load the grounding head saved with the checkpoint being resumed; a ConfigError when it has none."""
    if resume is not None and grounding is not None:
        from labrobfail_vlm.train.grounding import load_head

        if not load_head(grounding["head"], Path(resume)):  # a run made without grounding: its optimizer differs
            raise ConfigError(
                f"resume: {resume} was trained without frame grounding; resume it with "
                f"grounding.weight=0 grounding.pretrain_epochs=0"
            )
