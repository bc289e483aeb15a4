"""Fine-tune LabRobFail-VLM (Qwen3-VL): full vision encoder + merger, LoRA on the language decoder. The code behind
train.py and the `labrobfail-train` console script.

Run as:
    python train.py preset=tiny dataset_dir=outputs/demo_dataset output_dir=outputs/demo_train max_steps=50
    python train.py model.path=/models/Qwen3-VL-8B-Instruct dataset_dir=outputs/dataset output_dir=outputs/run
    python train.py preset=frozen_vision ...          # ablations: full | frozen_vision | no_index
    deepspeed --num_gpus 2 train.py deepspeed=configs/ds_zero3.json model.path=... dataset_dir=... output_dir=...
    python train.py ... resume=true                   # continue from the newest checkpoint (or stage-A epoch)

Defaults and presets: configs/train.yaml. Checkpoints: labrobfail_vlm/train/checkpoint.py.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from labrobfail_vlm.config import ConfigError, cli_main, is_int, load_config, make_dir
from labrobfail_vlm.io import atomic_write_json, swap_in
from labrobfail_vlm.train.resume import check_resume_settings, load_resumed_head, resume_point, run_settings


def _world_size() -> int:
    return int(os.environ.get("WORLD_SIZE", "1"))


def dataset_stats(dataset_dir: Any) -> Path:
    """The stats.json of a dataset built by labrobfail-build-dataset; a ConfigError for anything else."""
    stats = Path(dataset_dir or "") / "stats.json"
    if dataset_dir is None or not stats.is_file():
        raise ConfigError(f"dataset_dir: {dataset_dir!r} is not a dataset built by labrobfail-build-dataset")
    return stats


def _extra_train(cfg: Any) -> list[str]:
    """extra_train's dataset folders, after checking them and extra_repeat against the run (before anything loads)."""
    extra = cfg.extra_train or []
    if isinstance(extra, str) or not all(isinstance(d, str) for d in extra):
        raise ConfigError(f"extra_train: a list of dataset folders ('extra_train=[DIR,...]'), got {extra!r}")
    repeat = cfg.extra_repeat
    if not is_int(repeat, 1) or (repeat > 1 and not cfg.packing):
        raise ConfigError(f"extra_repeat: a positive integer, above 1 only with packing=true; got {repeat!r}")
    if extra and (float(cfg.grounding.weight) > 0 or cfg.augment.enabled):
        # both read per-trajectory data (frame targets, view counts) from dataset_dir's trajectories.json alone
        raise ConfigError("extra_train: not with grounding.weight > 0 or augment.enabled (they read dataset_dir only)")
    for d in extra:
        if not (Path(d) / "stats.json").is_file():
            raise ConfigError(f"extra_train: {d!r} is not a dataset built by labrobfail-build-dataset")
    return list(extra)


def _check_dataset(cfg: Any) -> dict[str, Any]:
    """The dataset's grid config, after checking it matches the run."""
    grid = json.loads(dataset_stats(cfg.dataset_dir).read_text()).get("grid", {})
    for d in _extra_train(cfg):  # one grid for every record the run trains on
        other = json.loads(dataset_stats(d).read_text()).get("grid", {})
        if other != grid:
            raise ConfigError(f"extra_train: {d} was built with grid {other}, {cfg.dataset_dir} with {grid}")
    drawn = grid.get("draw_index", True)
    if bool(drawn) != bool(cfg.grid_index):
        raise ConfigError(
            f"grid_index: the dataset was built with grid.draw_index={drawn}, the run expects "
            f"{cfg.grid_index} (the no_index preset needs a dataset built with grid.draw_index=false)"
        )
    return grid


def _drawing(cfg: Any) -> dict[str, Any] | None:
    """What the simulator drew into every grid the model learned from (labrobfail_vlm/drawing.py), for the
    checkpoint: the run's datasets and, for a stage that starts from a fine-tuned model, that model's."""
    from labrobfail_vlm import drawing
    from labrobfail_vlm.train.checkpoint import is_finetuned, trained_drawing

    dirs = [cfg.dataset_dir, *(cfg.extra_train or [])]
    seen = [json.loads(dataset_stats(d).read_text()).get("drawing") for d in dirs]
    parent = str(cfg.model.path)
    return drawing.merge(seen + ([trained_drawing(parent)] if is_finetuned(parent) else []))


def _augment(cfg: Any, grid: dict[str, Any]) -> Any:
    """Twin-consistent grid augmentation for training (labrobfail_vlm/augment.py), or None when off."""
    a = cfg.augment
    if not a.enabled:
        return None
    from labrobfail_vlm.augment import AugmentConfig
    from labrobfail_vlm.grid import GridConfig
    from labrobfail_vlm.train.data import GridAugment

    trajs = json.loads((Path(cfg.dataset_dir) / "trajectories.json").read_text())
    views = {t.get("views") for t in trajs}
    if len(views) != 1 or None in views:
        raise ConfigError("augment.enabled: the dataset's trajectories.json lacks one common 'views' count; rebuild it")
    return GridAugment(
        AugmentConfig.from_section(a),
        GridConfig.from_dict(grid),
        int(views.pop()),
        int(cfg.seed),
    )


def _grounding(cfg: Any, model: Any, grid: dict[str, Any]) -> tuple[dict[str, Any] | None, dict | None]:
    """The grounding head and its per-frame targets (labrobfail_vlm/train/grounding.py), or (None, None)."""
    g = cfg.grounding
    if float(g.weight) == 0:
        return None, None
    from labrobfail_vlm.grid import GridConfig
    from labrobfail_vlm.train.grounding import dataset_targets, make_head

    gcfg = GridConfig.from_dict(grid)
    trajs = json.loads((Path(cfg.dataset_dir) / "trajectories.json").read_text())
    targets, views = dataset_targets(trajs, gcfg)
    head = make_head(str(g.head), int(model.config.vision_config.out_hidden_size), gcfg, views)
    return {"head": head, "weight": float(g.weight), "rank": float(g.rank), "lr": float(g.lr)}, targets


def _curriculum(cfg: Any) -> tuple[bool, float, float]:
    """The curriculum's (pairs, polarity_warmup, detect_first), after checking the fractions are in [0, 1]."""
    pairs, warm = bool(cfg.curriculum.pairs), float(cfg.curriculum.polarity_warmup)
    detect = float(cfg.curriculum.detect_first)
    for key, v in (("polarity_warmup", warm), ("detect_first", detect)):
        if not 0.0 <= v <= 1.0:
            raise ConfigError(f"curriculum.{key}: a fraction of the steps in [0, 1], got {v}")
    return pairs, warm, detect


def _check_settings(cfg: Any, detect: float) -> int:
    """Check the grounding, tower cache, loss and model settings before anything is built (a bad value fails
    in seconds, not after the model loads); returns grounding.pretrain_epochs (stage A's epochs, 0: none)."""
    for key in ("weight", "rank", "lr", "pretrain_epochs"):
        if float(cfg.grounding[key]) < 0:
            raise ConfigError(f"grounding.{key}: must be >= 0, got {cfg.grounding[key]}")
    from labrobfail_vlm.train.grounding import check_head
    from labrobfail_vlm.train.tower_cache import check_cache_mb

    check_cache_mb(cfg.tower_cache_mb)

    check_head(str(cfg.grounding.head))  # before the model loads
    if not (float(cfg.epochs) > 0 or int(cfg.max_steps) > 0):  # else an untrained final/ would be written
        raise ConfigError(f"epochs: expected > 0 (or max_steps > 0), got {cfg.epochs!r}")
    pre_epochs = int(cfg.grounding.pretrain_epochs)
    if pre_epochs and float(cfg.grounding.weight) == 0:
        raise ConfigError("grounding.pretrain_epochs: needs grounding.weight > 0 (the head it trains)")
    if float(cfg.grounding.weight) > 0 and cfg.deepspeed is not None:  # the head lives outside DeepSpeed's engine
        raise ConfigError(
            f"grounding.weight: the grounding head and stage A run on one process, not under "
            f"deepspeed={cfg.deepspeed}; set grounding.weight=0 grounding.pretrain_epochs=0 (or "
            f"pre-train the tower in a separate run and pass its final/ as model.path)"
        )
    if detect and cfg.loss.mode != "record":
        raise ConfigError("curriculum.detect_first: needs loss.mode=record (it sets per-record loss weights)")
    if cfg.model.path is None:
        raise ConfigError("model.path: give a local Qwen3-VL directory (or use preset=tiny)")
    return pre_epochs


def _prepare_model_dir(cfg: Any) -> dict[str, Any]:
    """Build preset=tiny's model at model.path when it is not there yet (with the `tower` it names); returns the
    tower's provenance for the summary ({} when none was put in)."""
    from labrobfail_vlm.model.tower import read_card, resolve

    tower_dir = resolve(cfg.tower)
    if tower_dir is not None and cfg.preset != "tiny":
        raise ConfigError(
            f"tower: {cfg.tower} replaces the random tower of preset=tiny; a real checkpoint keeps its "
            "own (set tower=scratch)"
        )
    tower_info: dict[str, Any] = {}
    if tower_dir is not None and not Path(cfg.model.path).is_dir():
        card = read_card(tower_dir)  # before anything is built (a model.path that exists already has its tower)
        tower_info = {"path": str(cfg.tower), "sha256": card["sha256"], "parameters": card.get("parameters")}
    if (
        cfg.preset == "tiny"
        and Path(cfg.model.path) == Path(cfg.output_dir) / "tiny_base"
        and Path(cfg.model.path).is_dir()
    ):
        from labrobfail_vlm.model.tiny import check_built

        # The run's own random base, built by an earlier (or killed) run; a model.path named on the command line is
        # a trained model whose size tiny_arch does not describe.
        check_built(cfg.model.path, OmegaConf.to_container(cfg.tiny_arch.text))  # type: ignore[arg-type]
    if cfg.preset == "tiny" and not Path(cfg.model.path).is_dir():
        from labrobfail_vlm.model.tiny import build_tiny, dataset_texts

        # The vocabulary comes from this dataset's training text (task descriptions, object names).
        build_tiny(
            cfg.model.path,
            seed=int(cfg.seed),
            texts=dataset_texts(cfg.dataset_dir),
            vision=OmegaConf.to_container(cfg.tiny_arch.vision),  # type: ignore[arg-type]
            text=OmegaConf.to_container(cfg.tiny_arch.text),  # type: ignore[arg-type]
            tower=tower_dir,
        )
    return tower_info


def _dtype(cfg: Any) -> Any:
    """model.dtype as a torch dtype; a ConfigError for anything but bfloat16 or float32."""
    import torch

    dtype = {"bfloat16": torch.bfloat16, "float32": torch.float32}.get(cfg.model.dtype)
    if dtype is None:
        raise ConfigError(f"model.dtype: expected bfloat16 or float32, got {cfg.model.dtype!r}")
    return dtype


def _batch_split(cfg: Any) -> tuple[int, int]:
    """(per_device_batch, ranks), after checking global_batch divides evenly over them."""
    per_dev, world = int(cfg.per_device_batch), _world_size()
    if per_dev < 1 or int(cfg.global_batch) % (per_dev * world):
        raise ConfigError(
            f"global_batch: {cfg.global_batch} is not a multiple of per_device_batch x ranks ({per_dev} x {world})"
        )
    return per_dev, world


def _start_services(cfg: Any) -> None:
    """wandb's environment and DeepSpeed's process group, both needed before TrainingArguments is made."""
    import torch

    if cfg.wandb.enabled:
        os.environ.setdefault("WANDB_MODE", str(cfg.wandb.mode))
        os.environ.setdefault("WANDB_PROJECT", str(cfg.wandb.project))
        os.environ.setdefault("WANDB_DIR", str(Path(cfg.output_dir)))
        os.environ.setdefault("WANDB_SILENT", "true")
    if cfg.deepspeed is not None:
        if not Path(cfg.deepspeed).is_file():
            raise ConfigError(f"deepspeed: no such config file {cfg.deepspeed!r}")
        import deepspeed  # DeepSpeed's own process group: its config reads the world size from it

        deepspeed.init_distributed(dist_backend="nccl" if torch.cuda.is_available() else "gloo")


def _training_arguments(cfg: Any, dtype: Any, per_dev: int, world: int) -> Any:
    """The Trainer's TrainingArguments from the run's config, checked against the ranks actually up."""
    import torch
    from transformers import TrainingArguments

    args = TrainingArguments(
        output_dir=str(cfg.output_dir),
        per_device_train_batch_size=per_dev,
        gradient_accumulation_steps=int(cfg.global_batch) // (per_dev * world),
        num_train_epochs=float(cfg.epochs),
        max_steps=int(cfg.max_steps),
        lr_scheduler_type=str(cfg.scheduler),
        warmup_steps=float(cfg.warmup_ratio),
        learning_rate=float(cfg.lr.lora),
        weight_decay=float(cfg.weight_decay),
        logging_steps=int(cfg.logging_steps),
        save_steps=int(cfg.save_steps),
        save_total_limit=None if cfg.save_total_limit is None else int(cfg.save_total_limit),
        save_strategy="steps",
        report_to=["wandb"] if cfg.wandb.enabled else "none",
        seed=int(cfg.seed),
        bf16=dtype == torch.bfloat16 and torch.cuda.is_available(),
        remove_unused_columns=False,
        dataloader_num_workers=0,
        deepspeed=cfg.deepspeed,
        disable_tqdm=not cfg.progress,
        gradient_checkpointing=bool(cfg.gradient_checkpointing),
        use_cpu=not torch.cuda.is_available(),
        max_grad_norm=1.0,
        logging_first_step=True,
    )
    # Under ZeRO-3 the HfDeepSpeedConfig made by TrainingArguments must exist, and the process group be up
    # (reading world_size initialises it), before the model is built.
    if args.world_size != world:
        raise ConfigError(f"deepspeed: {args.world_size} ranks are up but WORLD_SIZE says {world}")
    return args


def _load_tuned_model(cfg: Any, dtype: Any) -> tuple[Any, Any, Any, Any]:
    """(processor, model, trainable counts, tower cache or None): the model loaded, set up for tuning (full
    vision + LoRA decoder per `tuning`), its zero-lr groups frozen, and its frozen tower cached when it can be."""
    from labrobfail_vlm.model.hybrid import apply_tuning, count_trainable, freeze_zero_lr
    from labrobfail_vlm.model.loading import load_model, load_processor

    processor = load_processor(cfg.model.path)
    processor.tokenizer.padding_side = "right"
    model = load_model(cfg.model.path, dtype)
    model.config.use_cache = False
    model = apply_tuning(model, str(cfg.tuning), dict(cfg.lora))
    freeze_zero_lr(model, dict(cfg.lr))
    counts = count_trainable(model)
    cache = None
    if not cfg.augment.enabled:  # an augmented grid is new every time: nothing to reuse
        from labrobfail_vlm.train.tower_cache import cache_frozen_tower

        cache = cache_frozen_tower(model, float(cfg.tower_cache_mb))
    return processor, model, counts, cache


def _build_trainer(
    cfg: Any,
    args: Any,
    model: Any,
    processor: Any,
    grid: dict[str, Any],
    curriculum: tuple[bool, float, float],
    cache: Any = None,
) -> tuple[Any, Any, dict[str, Any] | None]:
    """(trainer, progress log, grounding or None): the training set, its collator and curriculum callbacks, and
    the HybridTrainer that runs them."""
    from labrobfail_vlm.train.curriculum import AugmentEpoch, DetectFirst, PolarityWarmup, Rewording
    from labrobfail_vlm.train.data import Collator, VQADataset, answer_balance
    from labrobfail_vlm.train.packing import TrajectoryDataset
    from labrobfail_vlm.train.trainer import HybridTrainer, ProgressLog

    pairs, warm, detect = curriculum
    # packing: a trajectory's records share one row and one image encoding (labrobfail_vlm/train/packing.py);
    # per_device_batch and global_batch then count trajectories
    extra, repeat = list(cfg.extra_train or []), int(cfg.extra_repeat)  # checked by _check_dataset (run's first step)
    train = (
        TrajectoryDataset(cfg.dataset_dir, "train", extra, repeat)
        if cfg.packing
        else VQADataset(cfg.dataset_dir, "train", extra)
    )
    rewording = Rewording(train.group_of, pairs) if pairs or warm > 0 or detect > 0 else None
    records_per_item = sum(map(len, train.items)) / len(train) if cfg.packing else 1.0
    progress_log = ProgressLog(Path(cfg.output_dir), records_per_item)
    callbacks = [
        progress_log,
        *([PolarityWarmup(rewording, warm)] if rewording is not None and warm else []),
        *([DetectFirst(rewording, detect)] if rewording is not None and detect else []),
    ]
    grounding, targets = _grounding(cfg, model, grid)
    augment = _augment(cfg, grid)
    if augment is not None:
        callbacks.append(AugmentEpoch(augment))
    balance = answer_balance(train.records if cfg.packing else train, dict(cfg.loss.get("balance") or {}))
    trainer = HybridTrainer(
        model=model,
        args=args,
        train_dataset=train,
        data_collator=Collator(
            processor,
            int(cfg.max_length),
            dict(cfg.loss.question_weights) if cfg.loss.mode == "record" else None,
            rewording,
            targets,
            train.group_of,
            augment,
            cache,
            balance,
        ),
        processing_class=processor,
        group_lrs=dict(cfg.lr),
        base_model=str(cfg.model.path),
        tuning=str(cfg.tuning),
        loss_mode=str(cfg.loss.mode),
        grid=grid,
        drawing=_drawing(cfg),
        pair_batches=pairs,
        grounding=grounding,
        settings=run_settings(cfg),
        callbacks=callbacks,
    )
    return trainer, progress_log, grounding


def _stage_a(
    cfg: Any,
    model: Any,
    trainer: Any,
    grounding: Any,
    pre_epochs: int,
    resume_stage_a: bool,
    progress_log: Any,
) -> dict[str, float]:
    """Stage A: pre-train the vision tower with the grounding head alone; returns its metrics and clocks."""
    from labrobfail_vlm.train.grounding import STAGE_A_DIR, pretrain
    from labrobfail_vlm.train.resume import SETTINGS_FILE

    if not resume_stage_a:  # what a resume of a killed stage A is checked against (check_resume_settings)
        atomic_write_json(
            make_dir("output_dir", cfg.output_dir, STAGE_A_DIR) / STAGE_A_DIR / SETTINGS_FILE, run_settings(cfg)
        )
    wall, cpu = time.perf_counter(), time.process_time()
    pre = pretrain(
        model,
        grounding["head"],
        trainer.get_train_dataloader(),
        pre_epochs,  # type: ignore[index]
        float(cfg.grounding.lr),
        float(cfg.grounding.rank),
        bool(cfg.progress),
        state_dir=Path(cfg.output_dir),
        resume=resume_stage_a,
        augment=trainer.data_collator.augment,
    )
    pre |= {
        "epochs": pre_epochs,
        "wall_s": round(time.perf_counter() - wall, 1),
        "cpu_s": round(time.process_time() - cpu, 1),
    }
    progress_log.start_after(pre["wall_s"], pre["cpu_s"])  # the learning curve's clocks include stage A
    print(json.dumps({"grounding_pretrain": pre}), flush=True)
    return pre


def _summary(
    trainer: Any,
    result: Any,
    counts: Any,
    pre: dict[str, float],
    tower_info: dict[str, Any],
    cache: Any,
) -> dict[str, Any]:
    """train_summary.json's content: steps, losses, clocks, trainable parameters and what stage A and the tower
    cache report."""
    losses = [h["loss"] for h in trainer.state.log_history if "loss" in h]
    return {
        "global_step": trainer.state.global_step,
        "train_loss": result.training_loss,
        "train_s": round(float(result.metrics.get("train_runtime", 0.0)), 1),  # the Trainer's loop, wall clock
        "first_loss": losses[0] if losses else None,
        "last_loss": losses[-1] if losses else None,
        "trainable_parameters": counts,
        **({"grounding_pretrain": pre} if pre else {}),
        **({"tower": tower_info} if tower_info else {}),
        **({"tower_cache": cache.stats()} if cache is not None else {}),
    }


def run(cfg: Any) -> dict[str, Any]:
    """Train one run from its resolved config: check it, build the model and Trainer, run stage A (grounding
    pre-training) when asked, then the Trainer; writes final/ and train_summary.json and returns the summary."""
    from transformers import set_seed

    from labrobfail_vlm.train.trainer import check_loss_mode

    # Seed before anything random is made: the grounding head is initialised before the Trainer seeds, and a
    # run that starts from a checkpoint (model.path) builds nothing that would seed it (torch's start-up seed
    # differs from process to process here).
    set_seed(int(cfg.seed))
    grid = _check_dataset(cfg)
    check_loss_mode(str(cfg.loss.mode))  # before the model loads
    curriculum = _curriculum(cfg)
    pre_epochs = _check_settings(cfg, curriculum[2])
    check_resume_settings(cfg)  # before anything is built or written: a refused resume costs nothing
    tower_info = _prepare_model_dir(cfg)
    dtype = _dtype(cfg)
    per_dev, world = _batch_split(cfg)
    _start_services(cfg)
    args = _training_arguments(cfg, dtype, per_dev, world)
    processor, model, counts, cache = _load_tuned_model(cfg, dtype)
    if args.process_index == 0:
        print(json.dumps({"trainable_parameters": counts, "tuning": cfg.tuning, "preset": cfg.preset}), flush=True)
    trainer, progress_log, grounding = _build_trainer(cfg, args, model, processor, grid, curriculum, cache)
    resume, resume_stage_a = resume_point(cfg, pre_epochs, _dtype(cfg))
    load_resumed_head(resume, grounding)
    pre: dict[str, float] = {}
    if pre_epochs and resume is None:  # stage A; a resumed run's checkpoint already holds the grounded tower
        pre = _stage_a(cfg, model, trainer, grounding, pre_epochs, resume_stage_a, progress_log)
    result = trainer.train(resume_from_checkpoint=resume)
    # final/ is written beside and swapped in whole: a bench or server reading a reused output_dir's final/ (or a
    # kill while saving) never meets old and new weights under one manifest
    final = Path(cfg.output_dir) / "final"
    tmp = final.with_name("final.tmp")
    if args.process_index == 0:
        shutil.rmtree(tmp, ignore_errors=True)
    trainer.save_model(str(tmp))  # every rank (ZeRO-3 gathers the weights); rank 0 writes
    summary = _summary(trainer, result, counts, pre, tower_info, cache)
    if args.process_index == 0:
        swap_in(tmp, final)
        atomic_write_json(Path(cfg.output_dir) / "train_summary.json", summary)
        print(json.dumps(summary), flush=True)
    return summary


def resolve_config(argv: list[str]) -> Any:
    """train.yaml + preset + (preset tiny) the recipe of its kind of tower + the command line, which wins."""
    args = [a for a in argv if not a.startswith("--local_rank")]
    cfg = load_config("train.yaml", args)
    if cfg.preset == "tiny":
        kind = "scratch" if str(cfg.tower) == "scratch" else "pretrained"
        cfg = OmegaConf.merge(cfg, cfg.tiny_towers[kind], OmegaConf.from_dotlist(args))
    return cfg


def main(argv: list[str]) -> int:
    try:
        run(resolve_config(argv))
    finally:
        _release_shm_buffer()
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        # A rank that exits with its gloo process group alive can abort at interpreter shutdown ("terminate
        # called without an active exception", SIGABRT) once the run has already succeeded. Only after success:
        # tearing down while another rank still waits in a collective would hang instead.
        dist.destroy_process_group()
        _leave_distributed_run()
    return 0


def _release_shm_buffer() -> None:
    """Remove this rank's DeepSpeed CPU all-reduce segment from /dev/shm. DeepSpeed's shared-memory op (used when
    every rank is on one machine) creates one 69 MB segment per rank, named after the uid, MASTER_ADDR,
    MASTER_PORT and rank, and never unlinks it: each multi-rank CPU run left them in RAM-backed tmpfs (7 GB after
    27 test runs on a 24 GB machine). By the end of a run every rank has long mapped the others' segments, and a
    mapping outlives its name, so each rank unlinks its own."""
    addr, port, rank = (os.environ.get(k) for k in ("MASTER_ADDR", "MASTER_PORT", "RANK"))
    if addr and port and rank:
        Path("/dev/shm", f"deepspeed_allreduce_buffer_{os.getuid()}_{addr}_{port}_{rank}").unlink(missing_ok=True)


def _leave_distributed_run() -> None:
    """Exit a rank without the interpreter's shutdown. Even with the process group destroyed, a thread of
    DeepSpeed's CPU shared-memory op now and then aborts the C++ teardown (the same "terminate called ..."; exit
    250 in a fresh-clone CI run on a loaded machine) after the run succeeded and wrote everything atomically.
    What atexit would still do is done here: wandb's run is finished and stdio flushed."""
    wandb = sys.modules.get("wandb")
    if wandb is not None and getattr(wandb, "run", None) is not None:
        wandb.finish()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def cli() -> None:
    """The `labrobfail-train` console script (and train.py, which deepspeed launches)."""
    cli_main(main, __doc__)
