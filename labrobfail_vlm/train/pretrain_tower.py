"""Pretrain the Qwen3-VL vision tower and merger on dense per-frame simulator state (make tower).

Run as:
    labrobfail-pretrain-tower data.out_dir=outputs/tower/data out_dir=outputs/tower/run
    labrobfail-pretrain-tower ... export_dir=labrobfail_vlm/assets/tower     # ship it

Defaults: configs/tower.yaml. Trains on the seen training pairs of a dataset built by labrobfail-build-tower-data,
evaluates every target on held-out seen pairs after each epoch (and on the val-object and val-scene sets at
the end; the sealed test sets are never the tower's), checkpoints after each epoch (a rerun resumes from the last
one), then writes out_dir/tower.safetensors, tower.json (the card's data: config, targets, held-out accuracy,
command, sha256), TOWER_CARD.md and metrics.json.
"""

from __future__ import annotations

import json
import math
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from labrobfail_vlm.config import (
    ConfigError,
    cli_main,
    load_config,
    make_dir,
    refuse_other_settings,
    require_ints,
    settings_record,
)

EVAL_SETS = {
    "seen": ({"val"}, {"seen"}),
    "val_object": ((), {"val_object"}),
    "val_scene": ((), {"val_scene"}),
}


def _check(cfg: Any) -> None:
    require_ints(cfg, ("epochs", "batch_size", "max_eval", "eval_every"))
    sizes = ("depth", "hidden_size", "intermediate_size", "num_heads", "temporal_patch_size")
    require_ints(cfg.vision, sizes, 1, "vision.")  # a tower of depth -1 would train and export
    if not float(cfg.lr) > 0:
        raise ConfigError(f"lr: expected a positive number, got {cfg.lr!r}")
    if not all(OmegaConf.is_list(lay) for lay in cfg.layouts or [None]):
        raise ConfigError(f"layouts: expected lists of views, e.g. 'layouts=[[front,side]]', got {cfg.layouts!r}")
    if any(len(lay) != len(cfg.layouts[0]) for lay in cfg.layouts):
        raise ConfigError(f"layouts: expected view lists of one length, got {list(cfg.layouts)}")
    from labrobfail_vlm.grid import GridConfig

    g = GridConfig(**cfg.grid)
    rows, cols = g.shape(len(cfg.layouts[0]))
    cw, ch = g.width // cols, g.height // rows
    if cw != ch or cw % 32 or g.width % cols or g.height % rows:
        raise ConfigError(
            f"grid: {g.width}x{g.height} with {g.max_frames} frames in {g.columns} columns and "
            f"{len(cfg.layouts[0])} views makes {cw}x{ch} px cells; the tower needs square cells of a "
            "multiple of 32 px (whole merged tokens)"
        )


def _save(out: Path, tower: Any, heads: Any, opt: Any, state: dict[str, Any]) -> None:
    """The resume point, written into a fresh folder then swapped in (a kill never leaves half a checkpoint)."""
    import torch
    from safetensors.torch import save_file

    from labrobfail_vlm.io import atomic_write_json, swap_in

    tmp, final = out / "checkpoint.tmp", out / "checkpoint"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    save_file({k: v.contiguous() for k, v in tower.state_dict().items()}, str(tmp / "tower.safetensors"))
    save_file({k: v.contiguous() for k, v in heads.state_dict().items()}, str(tmp / "heads.safetensors"))
    torch.save(opt.state_dict(), tmp / "optimizer.pt")
    atomic_write_json(tmp / "state.json", state)
    swap_in(tmp, final)


# Settings a rerun may change and still resume: more epochs extend the run; the rest only report or export.
RESUME_FREE = ("epochs", "export_dir", "progress", "threads", "max_eval", "eval_every", "out_dir")


def _settings(cfg: Any, init_sha: str | None) -> dict[str, Any]:
    """What decides the trained weights, as the checkpoint records it: the config less RESUME_FREE and
    data.progress, the starting tower by its content (init's sha256), not its path."""
    conf = settings_record(cfg, RESUME_FREE)
    conf["data"].pop("progress", None)
    conf["init"] = init_sha
    return conf


def _resume(out: Path, tower: Any, heads: Any, opt: Any, settings: dict[str, Any]) -> dict[str, Any] | None:
    """The checkpoint's state, its weights and optimizer loaded; None for a fresh out_dir. A checkpoint trained with
    other settings (those it records: checkpoints written before this check record none) is refused before anything
    loads, so a changed augmentation or learning rate cannot continue a run as if it were the same one."""
    import torch
    from safetensors.torch import load_file

    from labrobfail_vlm.io import swapped

    ck = swapped(out / "checkpoint", "state.json")
    if not (ck / "state.json").is_file():
        return None
    state = json.loads((ck / "state.json").read_text())
    if "config" in state:
        record = f'{out / "checkpoint" / "state.json"}, "config"'
        refuse_other_settings(
            state["config"], settings, RESUME_FREE, out, record, "out_dir", "labrobfail-pretrain-tower"
        )
    tower.load_state_dict(load_file(str(ck / "tower.safetensors")))
    heads.load_state_dict(load_file(str(ck / "heads.safetensors")))
    opt.load_state_dict(torch.load(ck / "optimizer.pt", weights_only=True))
    return state


@dataclass
class Run:
    """What one pretraining run holds between epochs."""

    cfg: Any
    out: Path
    grid: Any
    layouts: list[list[str]]
    train: Any
    evals: dict[str, Any]
    tower: Any
    heads: Any
    opt: Any
    ip: Any
    state: dict[str, Any]
    init_sha: str | None

    @property
    def steps(self) -> int:
        return math.ceil(len(self.train) / int(self.cfg.batch_size))


def setup(cfg: Any) -> Run:
    """Data, tower (from `init` if given), heads and optimiser; resumed from out_dir's checkpoint when there is one."""
    import torch

    from labrobfail_vlm.grid import GridConfig
    from labrobfail_vlm.model.processor import image_processor
    from labrobfail_vlm.model.tower import load_visual, read_card
    from labrobfail_vlm.model.tower import resolve as tower_dir
    from labrobfail_vlm.train import tower as T

    train = T.TowerData(cfg.data.out_dir, {"train"}, {"seen"})
    if not len(train):
        raise ConfigError(f"data.out_dir: {cfg.data.out_dir} has no seen training trajectories")
    evals = {k: T.TowerData(cfg.data.out_dir, s, v, int(cfg.max_eval)) for k, (s, v) in EVAL_SETS.items()}
    _check_views(cfg, [r for d in (train, *evals.values()) for r in d.rows])
    out = make_dir("out_dir", cfg.out_dir)
    tower = T.build_tower(OmegaConf.to_container(cfg.vision), int(cfg.out_hidden_size), int(cfg.seed))
    init = None if cfg.init is None else tower_dir(str(cfg.init))
    init_sha = None
    if init is not None:  # before the resume check, so a checkpoint still wins
        init_sha = read_card(init)["sha256"]
        load_visual(tower, init)
    heads = T.TowerHeads(int(cfg.out_hidden_size), len(train.cell_names), len(train.token_names))
    params = list(tower.parameters()) + list(heads.parameters())
    opt = torch.optim.AdamW(params, lr=float(cfg.lr), weight_decay=float(cfg.weight_decay))
    settings = _settings(cfg, init_sha)
    resumed = _resume(out, tower, heads, opt, settings)
    if resumed:
        print(f"resuming after epoch {resumed['epoch']} (step {resumed['step']})", file=sys.stderr)
    return Run(
        cfg=cfg,
        out=out,
        grid=GridConfig(**cfg.grid),
        layouts=[list(lay) for lay in cfg.layouts],
        train=train,
        evals={k: d for k, d in evals.items() if len(d)},
        tower=tower,
        heads=heads,
        opt=opt,
        ip=image_processor(temporal_patch_size=int(cfg.vision.temporal_patch_size)),
        state={"epoch": 0, "step": 0, "metrics": [], "wall_s": 0.0, "cpu_s": 0.0, **(resumed or {})}
        | {"config": settings},
        init_sha=init_sha,
    )


def train_epoch(run: Run, epoch: int) -> dict[str, Any]:
    """One epoch over the seen training trajectories (a fresh layout and augmentation per sample); its row."""
    import numpy as np
    import torch
    from tqdm import tqdm

    from labrobfail_vlm.augment import Augment, AugmentConfig
    from labrobfail_vlm.train import tower as T

    cfg, train, state = run.cfg, run.train, run.state
    bs, steps, nviews = int(cfg.batch_size), run.steps, len(run.layouts[0])
    total = int(cfg.epochs) * steps
    warm = int(float(cfg.warmup_ratio) * int(cfg.epochs) * steps)  # as written before the split: same rounding
    aug_cfg = AugmentConfig.from_section(cfg.augment)
    pos_weight = float(run.grid.width // run.grid.columns // T.TOKEN_PX) ** 2 / 2
    cell_pos_weight = T.positive_weights(train) if cfg.balance_cells else None
    params = [p for g in run.opt.param_groups for p in g["params"]]
    w0, c0 = T.clock()
    rng = np.random.default_rng([int(cfg.seed), epoch])
    order, lay = rng.permutation(len(train)), rng.integers(len(run.layouts), size=len(train))
    run.tower.train()
    run.heads.train()
    parts: dict[str, list[float]] = {"cell": [], "token": []}
    bar = tqdm(total=steps, desc=f"tower epoch {epoch + 1}/{cfg.epochs}", disable=not cfg.progress)
    for b in range(steps):
        idx = order[b * bs : (b + 1) * bs]
        batch = T.collate(
            [train.sample(int(i), run.layouts[lay[i]], run.grid, Augment.draw(aug_cfg, nviews, rng)) for i in idx],
            run.ip,
        )
        zc, zt = T.readout(run.tower, run.heads, batch, run.grid, nviews)
        loss, p = T.tower_loss(zc, zt, batch, float(cfg.token_weight), pos_weight, cell_pos_weight)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        for g in run.opt.param_groups:
            g["lr"] = T.lr_at(int(state["step"]), total, warm, float(cfg.lr))
        run.opt.step()
        run.opt.zero_grad(set_to_none=True)
        state["step"] += 1
        for k in parts:
            parts[k].append(p[k])
        bar.update(1)
        bar.set_postfix(cell=f"{np.mean(parts['cell'][-50:]):.3f}", token=f"{np.mean(parts['token'][-50:]):.3f}")
    bar.close()
    w1, c1 = T.clock()
    return {
        "epoch": epoch + 1,
        "step": state["step"],
        "loss_cell": round(float(np.mean(parts["cell"])), 4),
        "loss_token": round(float(np.mean(parts["token"])), 4),
        "wall_s": round(state["wall_s"] + w1 - w0, 1),
        "cpu_s": round(state["cpu_s"] + c1 - c0, 1),
    }


def log_row(row: dict[str, Any]) -> None:
    """One JSON line per epoch: the losses, clocks and (when evaluated) the seen held-out detection and accuracy."""
    seen = row.get("seen")
    extra = (
        {
            "seen_detection": seen.get("detection"),
            "seen_balanced": {k: v["balanced"] for k, v in seen["cells"].items()},
        }
        if seen
        else {}
    )
    print(json.dumps({k: v for k, v in row.items() if k != "seen"} | extra), flush=True)


def finish(run: Run, argv: list[str]) -> dict[str, Any]:
    """Every held-out set in every layout, then tower.safetensors, tower.json and TOWER_CARD.md (and the export)."""
    from labrobfail_vlm.io import atomic_write_bytes
    from labrobfail_vlm.train import tower as T
    from labrobfail_vlm.train.tower_card import card_data, card_markdown

    cfg = run.cfg
    heldout = {
        "+".join(lay): {k: T.evaluate(run.tower, run.heads, d, lay, run.grid, run.ip) for k, d in run.evals.items()}
        for lay in run.layouts
    }
    card = card_data(cfg, argv, run.train, run.evals, heldout, run.state, run.init_sha)
    card = T.export(run.tower, run.out, card)
    atomic_write_bytes(run.out / T.CARD_MD, card_markdown(card).encode())
    if cfg.export_dir:
        dest = Path(cfg.export_dir)
        dest.mkdir(parents=True, exist_ok=True)
        for f in (T.TOWER_FILE, T.CARD_FILE, T.CARD_MD):
            shutil.copyfile(run.out / f, dest / (f + ".tmp"))
            (dest / (f + ".tmp")).replace(dest / f)
    return card


def _check_views(cfg: Any, rows: list[dict[str, Any]]) -> None:
    """Every layout's views in every trajectory, before a folder is made (else the first grid that lacks one stops
    the run after an epoch's checkpoint)."""
    have = set.intersection(*(set(r["views"]) for r in rows))
    missing = sorted({str(v) for lay in cfg.layouts for v in lay} - have)
    if missing:
        raise ConfigError(
            f"layouts: views {missing} are not in every trajectory of {cfg.data.out_dir} (it has {sorted(have)}; "
            "generate with backend_kwargs.wrist=true for a wrist layout)"
        )


def main(argv: list[str]) -> int:
    import torch

    from labrobfail_vlm.io import atomic_write_json
    from labrobfail_vlm.train import tower as T

    cfg = load_config("tower.yaml", argv)
    _check(cfg)
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    run = setup(cfg)
    for epoch in range(int(run.state["epoch"]), int(cfg.epochs)):
        row = train_epoch(run, epoch)
        if "seen" in run.evals and ((epoch + 1) % int(cfg.eval_every) == 0 or epoch + 1 == int(cfg.epochs)):
            row["seen"] = T.evaluate(run.tower, run.heads, run.evals["seen"], run.layouts[0], run.grid, run.ip)
        run.state.update(epoch=epoch + 1, wall_s=row["wall_s"], cpu_s=row["cpu_s"])
        run.state["metrics"].append(row)
        log_row(row)
        _save(run.out, run.tower, run.heads, run.opt, run.state)
        atomic_write_json(run.out / "metrics.json", run.state["metrics"])
    card = finish(run, argv)
    print(json.dumps({"tower": str(run.out / T.TOWER_FILE), "bytes": card["bytes"], "sha256": card["sha256"]}))
    return 0


def cli() -> None:
    """The `labrobfail-pretrain-tower` console script."""
    cli_main(main, __doc__)
