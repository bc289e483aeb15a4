"""ACT training: record the demonstrations (cached in demos.npz), then optimise under a wall-clock budget."""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from labrobfail_vlm.augment import AugmentConfig
from labrobfail_vlm.config import ConfigError, make_dir
from labrobfail_vlm.io import atomic_write_bytes, atomic_write_json
from sim_backends.policies.act.checkpoint import last_progress, load_progress, save_checkpoint, save_progress
from sim_backends.policies.act.configuration_act import ACTConfig
from sim_backends.policies.act.data import DemoDataset, normalisation, record_demo
from sim_backends.types import WRIST

IDENTITY = (
    "task",
    "demos",
    "seed",
    "variant",
    "backend",
    "backend_kwargs",
    "max_dist",
    "max_angle",
    "noise",
    "carry_noise",
)


def _identity(cfg: DictConfig) -> dict[str, Any]:
    d = OmegaConf.to_container(cfg, resolve=True)
    return {**{k: d[k] for k in IDENTITY}, "cameras": d["model"]["cameras"], "image_size": d["model"]["image_size"]}


REGRASP_SEEDS = 1_000_000  # regrasp demonstrations draw seeds from `seed` + this on (none shared with the others)


def load_or_record(cfg: DictConfig, family: Any, out: Path) -> tuple[list[dict[str, np.ndarray]], dict[str, Any]]:
    """The demonstrations (demos.npz), plus `regrasp_demos` that start from a corrected grasp (demos_regrasp.npz,
    a cache of its own, so adding them keeps the plain demonstrations recorded before)."""
    demos, info = _cached_or_recorded(cfg, family, out / "demos.npz", _identity(cfg), int(cfg.demos))
    if int(cfg.regrasp_demos) > 0:
        ident = _identity(cfg) | {"regrasp_demos": int(cfg.regrasp_demos), "miss": float(cfg.miss)}
        extra, more = _cached_or_recorded(
            cfg, family, out / "demos_regrasp.npz", ident, int(cfg.regrasp_demos), float(cfg.miss)
        )
        demos, info = demos + extra, info | {"regrasp": more}
    return demos, info


def _cached_or_recorded(
    cfg: DictConfig, family: Any, path: Path, ident: dict[str, Any], n: int, miss: float = 0.0
) -> tuple[list[dict[str, np.ndarray]], dict[str, Any]]:
    """The cached demos when they were recorded with the same settings, else record `n` (atomically)."""
    from sim_backends.registry import backend_options, make_backend

    if path.is_file():
        with np.load(path, allow_pickle=False) as z:
            if json.loads(str(z["identity"])) == ident:
                bounds = z["bounds"]
                # z[k] decompresses the whole array on every access: read each once, then slice views of it
                arrays = {k: z[k] for k in ("images", "state", "action")}
                demos = [{k: v[a:b] for k, v in arrays.items()} for a, b in zip(bounds[:-1], bounds[1:])]
                return demos, json.loads(str(z["info"]))
    t0 = time.perf_counter()
    cams = [str(c) for c in cfg.model.cameras]
    section = dict(OmegaConf.to_container(cfg.backend_kwargs, resolve=True) or {})
    if WRIST in cams:  # the wrist view is a backend option, not one of its fixed cameras
        section["wrist"] = True
    src = make_backend(
        cfg.backend,
        image_size=int(cfg.model.image_size),
        cameras=[c for c in cams if c != WRIST],
        **backend_options(cfg.backend, section),
    )
    demos, tried = [], 0
    bar = tqdm(total=n, desc="regrasp demos" if miss else "demos", unit="demo", disable=not cfg.progress)
    first = int(cfg.seed) + (REGRASP_SEEDS if miss else 0)
    try:
        while len(demos) < n and tried < 3 * n:
            scenario = family.scenarios[tried % len(family.scenarios)]
            d = record_demo(
                src,
                family.plan,
                family.success,
                scenario,
                first + tried,
                cfg.variant,
                cams,
                float(cfg.max_dist),
                float(cfg.max_angle),
                float(cfg.noise),
                float(cfg.carry_noise),
                miss,
            )
            tried += 1
            if d is not None:
                demos.append(d)
                bar.update(1)
    finally:
        bar.close()
        src.close()
    if not demos:
        raise ConfigError(f"task: no successful demonstration of {family.name!r} in {tried} tries")
    info = {
        "recorded": len(demos),
        "tried": tried,
        "record_s": round(time.perf_counter() - t0, 1),
        "ticks": int(sum(len(d["action"]) for d in demos)),
    }
    bounds = np.cumsum([0] + [len(d["action"]) for d in demos])
    import io

    buf = io.BytesIO()
    np.savez(
        buf,
        identity=json.dumps(ident),
        info=json.dumps(info),
        bounds=bounds,
        **{k: np.concatenate([d[k] for d in demos]) for k in ("images", "state", "action")},
    )
    atomic_write_bytes(path, buf.getvalue())
    return demos, info


RESUME_FREE = ("max_minutes", "save_every", "log_every", "threads")  # train settings a resumed run may change


def augment_config(section: Any) -> AugmentConfig | None:
    """train.augment -> the draw's settings, or None when disabled; a bad value is a ConfigError."""
    if not section.enabled:
        return None
    try:
        return AugmentConfig.from_section(section)
    except ValueError as e:
        raise ConfigError(f"train.{e}") from None


def _model_config(cfg: DictConfig) -> ACTConfig:
    """Create out_dir and read the model section; either failing is a ConfigError (before any recording)."""
    make_dir("out_dir", cfg.out_dir)
    try:
        return ACTConfig(**OmegaConf.to_container(cfg.model, resolve=True))  # type: ignore[arg-type]
    except (TypeError, ValueError) as e:
        raise ConfigError(str(e)) from None


def _optimiser(model: Any, t: DictConfig) -> tuple[Any, Any]:
    """(AdamW, its learning-rate schedule): the backbone gets its own rate (train.lr_backbone)."""
    import torch

    backbone = [p for n, p in model.named_parameters() if n.startswith("backbone.")]
    rest = [p for n, p in model.named_parameters() if not n.startswith("backbone.")]
    opt = torch.optim.AdamW(
        [{"params": rest, "lr": float(t.lr)}, {"params": backbone, "lr": float(t.lr_backbone)}],
        weight_decay=float(t.weight_decay),
    )
    # cosine: warm up, then anneal to 0 over train.steps (a wall-clock stop before then leaves it part-annealed)
    from transformers import get_constant_schedule_with_warmup, get_cosine_schedule_with_warmup

    warmup = int(t.warmup)
    sched = (
        get_cosine_schedule_with_warmup(opt, warmup, int(t.steps))
        if t.schedule == "cosine"
        else get_constant_schedule_with_warmup(opt, warmup)
    )
    return opt, sched


@dataclass
class _Run:
    """What the training loop reads and updates: the model, its optimiser and data, and where it stands (so a
    resumed run picks up all of it from a checkpoint)."""

    model: Any
    model_cfg: ACTConfig
    opt: Any
    sched: Any
    data: DemoDataset
    order: Any  # the loader's torch.Generator
    loader: Any
    same: dict[str, Any]  # the train settings a resumed run must share
    out: Path
    curve: list[dict[str, float]] = field(default_factory=list)
    step: int = 0
    done_s: float = 0.0
    skip: int = 0  # batches of the resumed epoch already trained on
    rng_after: Any = None  # torch's RNG state after the last of them


def _resume(r: _Run) -> None:
    """Load the newest complete checkpoint into `r`; a ConfigError when there is none or its settings differ."""
    last = last_progress(r.out / "checkpoints")
    if last is None:
        raise ConfigError(f"resume: no complete checkpoint under {r.out / 'checkpoints'}")
    tensors, saved = load_progress(r.model, last)
    if saved["train"] != r.same or saved["model"] != r.model_cfg.to_dict():
        raise ConfigError(f"resume: {last} was trained with other settings; rerun without resume=true")
    r.opt.load_state_dict(tensors["opt"])
    r.sched.load_state_dict(tensors["sched"])
    r.order.set_state(tensors["order"])  # the epoch's shuffle, then its first batches skipped (loaded, not used)
    r.data.rng.bit_generator.state = saved["augment_rng"]
    r.step, r.done_s, r.skip, r.curve = saved["step"], saved["seconds"], saved["batch"], saved["curve"]
    r.rng_after = tensors["rng"]


def _save_progress(r: _Run, at_epoch: dict[str, Any], batch: int, t0: float) -> None:
    """Write checkpoints/step-N: the model plus everything a resumed run needs to go on exactly as this one."""
    import torch

    save_progress(
        r.model,
        r.model_cfg,
        r.out / "checkpoints" / f"step-{r.step}",
        {"opt": r.opt.state_dict(), "sched": r.sched.state_dict(), "rng": torch.get_rng_state()}
        | {"order": at_epoch["order"]},
        {
            "step": r.step,
            "batch": batch,
            "seconds": time.perf_counter() - t0,
            "augment_rng": at_epoch["augment_rng"],
            "curve": r.curve,
            "train": r.same,
            "model": r.model_cfg.to_dict(),
        },
    )


def _optimise(r: _Run, t: DictConfig, t0: float, budget: float, progress: bool) -> None:
    """The training loop: steps until train.steps or the wall-clock budget, logging and checkpointing as it goes."""
    import torch

    bar = tqdm(total=int(t.steps), initial=r.step, desc="train", unit="step", disable=not progress)
    r.model.train()
    while r.step < int(t.steps) and time.perf_counter() - t0 < budget:
        at_epoch = {"order": r.order.get_state(), "augment_rng": r.data.rng.bit_generator.state}
        for batch, (images, state, actions, pad, points) in enumerate(r.loader, 1):
            if r.skip:
                r.skip -= 1
                if not r.skip:
                    torch.set_rng_state(r.rng_after)  # dropout and the CVAE draws go on as they would have
                continue
            loss, parts = r.model.loss(images, state, actions, pad, points)
            r.opt.zero_grad(set_to_none=True)
            loss.backward()
            r.opt.step()
            lr = r.sched.get_last_lr()[0]  # the rate this step used
            r.sched.step()
            r.step += 1
            bar.update(1)
            if r.step % int(t.log_every) == 0 or r.step == 1:
                r.curve.append({"step": r.step, "minutes": round((time.perf_counter() - t0) / 60, 3), "lr": lr} | parts)
            if r.step % int(t.save_every) == 0:
                _save_progress(r, at_epoch, batch, t0)
            if r.step >= int(t.steps) or time.perf_counter() - t0 >= budget:
                break
    bar.close()


def train(cfg: DictConfig, family: Any) -> dict[str, Any]:
    """Record (or reuse) the demonstrations, then train ACT on them under train.max_minutes, resuming from the
    newest checkpoint when resume=true; writes final/ and train_log.json and returns the log."""
    import torch
    from torch.utils.data import DataLoader

    from sim_backends.policies.act.modeling_act import ACTModel

    out = Path(cfg.out_dir)
    model_cfg = _model_config(cfg)
    demos, info = load_or_record(cfg, family, out)
    model_cfg.stats = normalisation(demos)
    t = cfg.train
    torch.manual_seed(int(t.seed))
    torch.set_num_threads(int(t.threads))
    model = ACTModel(model_cfg)
    opt, sched = _optimiser(model, t)
    data = DemoDataset(demos, model_cfg, augment_config(t.augment), int(t.seed), bool(t.hold_end))
    order = torch.Generator().manual_seed(int(t.seed))  # the loader's shuffles, one draw per epoch
    loader = DataLoader(data, batch_size=int(t.batch_size), shuffle=True, drop_last=True, generator=order)
    same = {k: v for k, v in OmegaConf.to_container(t, resolve=True).items() if k not in RESUME_FREE}  # type: ignore[union-attr]
    r = _Run(model, model_cfg, opt, sched, data, order, loader, same, out)
    if cfg.resume:
        _resume(r)
    step0 = r.step
    t0, budget = time.perf_counter() - r.done_s, float(t.max_minutes) * 60
    _optimise(r, t, t0, budget, bool(cfg.progress))
    if r.step < int(t.steps):  # a busy machine can run out the clock: this ACT is not the step count's
        tqdm.write(
            f"warning: train.max_minutes ran out at step {r.step} of {int(t.steps)}; this ACT differs from a full "
            "run's (resume=true with a larger train.max_minutes finishes it)",
            file=sys.stderr,
        )
    save_checkpoint(model.eval(), model_cfg, out / "final")
    summary = {
        "task": family.name,
        "demos": info,
        "steps": r.step,
        **({"resumed_at_step": step0} if step0 else {}),
        "train_minutes": round((time.perf_counter() - t0) / 60, 2),
        "samples": r.step * int(t.batch_size),
        "parameters": sum(p.numel() for p in model.parameters()),
        "final": str(out / "final"),
        "curve": r.curve,
    }
    atomic_write_json(out / "train_log.json", summary)
    return summary
