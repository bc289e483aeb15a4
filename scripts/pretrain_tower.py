"""Pretrain the Qwen3-VL vision tower and merger on dense per-frame simulator state (make tower).

Run as:
    python scripts/pretrain_tower.py data.out_dir=outputs/tower/data out_dir=outputs/tower/run
    python scripts/pretrain_tower.py ... export_dir=labrobfail_vlm/assets/tower     # ship it

Defaults: configs/tower.yaml. Trains on the seen training pairs of a dataset built by scripts/build_tower_data.py,
evaluates every target on held-out seen pairs after each epoch (and on the val-object and val-scene sets at
the end; the sealed test sets are never the tower's), checkpoints after each epoch (a rerun resumes from the last
one), then writes out_dir/tower.safetensors,
tower.json (the card's data: config, targets, held-out accuracy, command, sha256), TOWER_CARD.md and metrics.json.
"""

from __future__ import annotations

import json
import math
import shlex
import shutil
import sys
from pathlib import Path
from typing import Any

from labrobfail_vlm.config import ConfigError, cli_main, load_config, require_ints

EVAL_SETS = {
    "seen": ({"val"}, {"seen"}),
    "val_object": ((), {"val_object"}),
    "val_scene": ((), {"val_scene"}),
}


def _check(cfg: Any) -> None:
    require_ints(cfg, ("epochs", "batch_size", "max_eval", "eval_every"))
    if not float(cfg.lr) > 0:
        raise ConfigError(f"lr: expected a positive number, got {cfg.lr!r}")
    if not cfg.layouts or any(len(lay) != len(cfg.layouts[0]) for lay in cfg.layouts):
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

    from labrobfail_vlm.io import atomic_write_json

    tmp, final = out / "checkpoint.tmp", out / "checkpoint"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    save_file({k: v.contiguous() for k, v in tower.state_dict().items()}, str(tmp / "tower.safetensors"))
    save_file({k: v.contiguous() for k, v in heads.state_dict().items()}, str(tmp / "heads.safetensors"))
    torch.save(opt.state_dict(), tmp / "optimizer.pt")
    atomic_write_json(tmp / "state.json", state)
    old = out / "checkpoint.old"
    shutil.rmtree(old, ignore_errors=True)
    if final.exists():
        final.rename(old)
    tmp.rename(final)
    shutil.rmtree(old, ignore_errors=True)


def _resume(out: Path, tower: Any, heads: Any, opt: Any) -> dict[str, Any] | None:
    import torch
    from safetensors.torch import load_file

    ck = out / "checkpoint"
    if not (ck / "state.json").is_file():
        return None
    tower.load_state_dict(load_file(str(ck / "tower.safetensors")))
    heads.load_state_dict(load_file(str(ck / "heads.safetensors")))
    opt.load_state_dict(torch.load(ck / "optimizer.pt", weights_only=True))
    return json.loads((ck / "state.json").read_text())


def shard_origin(shard_dir: str) -> str:
    """How a shard folder was generated (its run.json), in words for the card: the variant, seed and any scene family
    other than the variant's own, so a reader sees which frames were domain-randomised."""
    try:
        run = json.loads((Path(shard_dir) / "run.json").read_text())
    except (OSError, ValueError):
        return shard_dir
    family = (run.get("backend_kwargs") or {}).get("scene_family")
    return f"{shard_dir} ({run.get('variant')}, seed {run.get('seed')}" + (
        f", scene family {family})" if family else ")"
    )


def card_markdown(card: dict[str, Any]) -> str:
    """TOWER_CARD.md: what the tower is, what it learned from, how well it reads each target held out."""
    v = card["vision_config"]
    lines = [
        "# The LabRobFail vision tower (sim-pretrained)",
        "",
        f"A Qwen3-VL vision tower and merger ({card['parameters']:,} parameters, {card['bytes'] / 1e6:.1f} MB "
        f"float32 safetensors; depth {v['depth']}, width {v['hidden_size']}, MLP {v['intermediate_size']}, "
        f"{v['num_heads']} heads, 16 px patches merged 2x2, output {v['out_hidden_size']} = the tiny decoder's "
        "width), pretrained on rendered frames with exact simulator state. Made by `make tower`; "
        "`make demo` and `make reproduce` start from it (`tower=scratch` keeps the random tower).",
        "",
        "## Data",
        "",
        card["data_summary"],
        "",
        "## Targets",
        "",
        "Per frame and view, from simulator state (data/frame_targets.py): "
        + ", ".join(card["targets"]["cells"])
        + "; and per 32 px token, where the "
        + ", ".join(card["targets"]["tokens"])
        + " project. Never from the injected perturbation.",
        "",
        "## Held-out accuracy",
        "",
        "Cell targets: balanced accuracy (mean recall of the two classes; 0.5 = chance) over the cells where "
        "the target applies, and the positive rate. Token targets: how often the cell's top-scoring token "
        "holds the point, against chance. Seen = held-out pairs of the seen catalogue; val object and "
        "val scene = the simulator's validation variants (episodes of their own), never trained on.",
        "",
    ]
    for lay, sets in card["heldout"].items():
        names = list(sets)
        if not names:
            continue
        lines += [f"### Layout {lay}", "", "| target | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
        first = sets[names[0]]
        for t in first["cells"]:
            lines.append(
                f"| {t} | "
                + " | ".join(
                    f"{s['cells'][t]['balanced']:.3f} (pos {s['cells'][t]['positive']:.2f})" if t in s["cells"] else "–"
                    for s in sets.values()
                )
                + " |"
            )
        for t in first["tokens"]:
            lines.append(
                f"| position: {t} | "
                + " | ".join(
                    f"{s['tokens'][t]['top1']:.3f} (chance {s['tokens'][t]['chance']:.2f})" if t in s["tokens"] else "–"
                    for s in sets.values()
                )
                + " |"
            )
        lines.append(
            "| detection (last frame, failed_by_now) | "
            + " | ".join(
                f"{s['detection']['accuracy']:.3f} (majority {s['detection']['majority']:.3f})"
                if "detection" in s
                else "–"
                for s in sets.values()
            )
            + " |"
        )
        lines.append("")
    lines += [
        "## Use",
        "",
        card["use"],
        "",
        "## Reproduce",
        "",
        *(
            [f"Started from the tower with sha256 `{card['training']['init_sha256']}` (its own card says how).", ""]
            if card["training"].get("init_sha256")
            else []
        ),
        f"```\n{card['command']}\n```",
        "",
        f"sha256 of {card['file']}: `{card['sha256']}`",
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    import numpy as np
    import torch
    from omegaconf import OmegaConf
    from tqdm import tqdm

    from labrobfail_vlm.augment import Augment, AugmentConfig
    from labrobfail_vlm.grid import GridConfig
    from labrobfail_vlm.io import atomic_write_bytes, atomic_write_json
    from labrobfail_vlm.model.processor import image_processor
    from labrobfail_vlm.model.tower import load_visual, read_card
    from labrobfail_vlm.model.tower import resolve as tower_dir
    from labrobfail_vlm.train import tower as T

    cfg = load_config("tower.yaml", argv)
    _check(cfg)
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    grid = GridConfig(**cfg.grid)
    vision = OmegaConf.to_container(cfg.vision)
    aug_cfg = AugmentConfig.from_section(cfg.augment)
    layouts = [list(lay) for lay in cfg.layouts]
    train = T.TowerData(cfg.data.out_dir, {"train"}, {"seen"})
    if not len(train):
        raise ConfigError(f"data.out_dir: {cfg.data.out_dir} has no seen training trajectories")
    evals = {k: T.TowerData(cfg.data.out_dir, s, v, int(cfg.max_eval)) for k, (s, v) in EVAL_SETS.items()}
    evals = {k: d for k, d in evals.items() if len(d)}
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tower = T.build_tower(vision, int(cfg.out_hidden_size), int(cfg.seed))
    init = None if cfg.init is None else tower_dir(str(cfg.init))
    init_sha = None
    if init is not None:  # before the resume check, so a checkpoint still wins
        init_sha = read_card(init)["sha256"]
        load_visual(tower, init)
    heads = T.TowerHeads(int(cfg.out_hidden_size), len(train.cell_names), len(train.token_names))
    params = list(tower.parameters()) + list(heads.parameters())
    opt = torch.optim.AdamW(params, lr=float(cfg.lr), weight_decay=float(cfg.weight_decay))
    ip = image_processor(temporal_patch_size=int(cfg.vision.temporal_patch_size))
    bs = int(cfg.batch_size)
    steps = math.ceil(len(train) / bs)
    total, warm = int(cfg.epochs) * steps, int(float(cfg.warmup_ratio) * int(cfg.epochs) * steps)
    resumed = _resume(out, tower, heads, opt)
    state = resumed or {"epoch": 0, "step": 0, "metrics": [], "wall_s": 0.0, "cpu_s": 0.0}
    if resumed:
        print(f"resuming after epoch {state['epoch']} (step {state['step']})", file=sys.stderr)
    pos_weight = float(grid.width // grid.columns // T.TOKEN_PX) ** 2 / 2
    cell_pos_weight = T.positive_weights(train) if cfg.balance_cells else None
    for epoch in range(int(state["epoch"]), int(cfg.epochs)):
        w0, c0 = T.clock()
        rng = np.random.default_rng([int(cfg.seed), epoch])
        order, lay = rng.permutation(len(train)), rng.integers(len(layouts), size=len(train))
        tower.train()
        heads.train()
        parts: dict[str, list[float]] = {"cell": [], "token": []}
        bar = tqdm(total=steps, desc=f"tower epoch {epoch + 1}/{cfg.epochs}", disable=not cfg.progress)
        for b in range(steps):
            idx = order[b * bs : (b + 1) * bs]
            batch = T.collate(
                [train.sample(int(i), layouts[lay[i]], grid, Augment.draw(aug_cfg, len(layouts[0]), rng)) for i in idx],
                ip,
            )
            zc, zt = T.readout(tower, heads, batch, grid, len(layouts[0]))
            loss, p = T.tower_loss(zc, zt, batch, float(cfg.token_weight), pos_weight, cell_pos_weight)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, 1.0)
            for g in opt.param_groups:
                g["lr"] = T.lr_at(int(state["step"]), total, warm, float(cfg.lr))
            opt.step()
            opt.zero_grad(set_to_none=True)
            state["step"] += 1
            for k in parts:
                parts[k].append(p[k])
            bar.update(1)
            bar.set_postfix(cell=f"{np.mean(parts['cell'][-50:]):.3f}", token=f"{np.mean(parts['token'][-50:]):.3f}")
        bar.close()
        w1, c1 = T.clock()
        row: dict[str, Any] = {
            "epoch": epoch + 1,
            "step": state["step"],
            "loss_cell": round(float(np.mean(parts["cell"])), 4),
            "loss_token": round(float(np.mean(parts["token"])), 4),
            "wall_s": round(state["wall_s"] + w1 - w0, 1),
            "cpu_s": round(state["cpu_s"] + c1 - c0, 1),
        }
        if "seen" in evals and ((epoch + 1) % int(cfg.eval_every) == 0 or epoch + 1 == int(cfg.epochs)):
            row["seen"] = T.evaluate(tower, heads, evals["seen"], layouts[0], grid, ip)
        state.update(epoch=epoch + 1, wall_s=row["wall_s"], cpu_s=row["cpu_s"])
        state["metrics"].append(row)
        print(
            json.dumps(
                {k: v for k, v in row.items() if k != "seen"}
                | (
                    {
                        "seen_detection": row["seen"].get("detection"),
                        "seen_balanced": {k: v["balanced"] for k, v in row["seen"]["cells"].items()},
                    }
                    if "seen" in row
                    else {}
                )
            ),
            flush=True,
        )
        _save(out, tower, heads, opt, state)
        atomic_write_json(out / "metrics.json", state["metrics"])
    heldout = {
        "+".join(lay): {k: T.evaluate(tower, heads, d, lay, grid, ip) for k, d in evals.items()} for lay in layouts
    }
    index = json.loads((Path(cfg.data.out_dir) / "index.json").read_text())
    frames = sum(int(r["frames"]) * len(r["views"]) for r in train.rows)
    card = {
        "vision_config": T.vision_config(vision, int(cfg.out_hidden_size)).to_dict(),
        "out_hidden_size": int(cfg.out_hidden_size),
        "grid": dict(cfg.grid),
        "layouts": layouts,
        "image_processor": {
            "patch_size": 16,
            "merge_size": 2,
            "temporal_patch_size": int(cfg.vision.temporal_patch_size),
        },
        "targets": {"cells": train.cell_names, "tokens": train.token_names},
        "data": {
            "shards": index["shards"],
            "trajectories": index["trajectories"],
            "failures": index["failures"],
            "training_trajectories": len(train),
            "training_view_frames": frames,
        },
        "data_summary": (
            f"{len(train):,} seen training trajectories ({frames:,} view-frames of "
            f"{index['image_size']} px, views {sorted({v for r in train.rows for v in r['views']})}) "
            f"from {', '.join(shard_origin(s) for s in index['shards'])}; held out: "
            + ", ".join(f"{k} {len(d)}" for k, d in evals.items())
            + " trajectories."
        ),
        "training": {
            k: cfg[k]
            for k in (
                "epochs",
                "batch_size",
                "lr",
                "warmup_ratio",
                "weight_decay",
                "token_weight",
                "balance_cells",
                "seed",
                "init",
            )
        }
        | {"augment": dict(cfg.augment), "init_sha256": init_sha, "wall_s": state["wall_s"], "cpu_s": state["cpu_s"]},
        "heldout": heldout,
        "use": (
            "The tiny Qwen3-VL of `preset=tiny` (train.py) takes this tower and merger in place of its random "
            "ones (`tower=shipped`, the default; `tower=scratch` or a folder holding tower.safetensors + "
            "tower.json). A real Qwen3-VL keeps its own pretrained tower: its card's targets are a recipe "
            "for sim-specific pretraining of that tower (same data, same heads) before the hybrid fine-tune."
        ),
        "command": " ".join(shlex.quote(a) for a in ["python", "scripts/pretrain_tower.py", *argv]),
    }
    card = T.export(tower, out, card)
    atomic_write_bytes(out / T.CARD_MD, card_markdown(card).encode())
    if cfg.export_dir:
        dest = Path(cfg.export_dir)
        dest.mkdir(parents=True, exist_ok=True)
        for f in (T.TOWER_FILE, T.CARD_FILE, T.CARD_MD):
            shutil.copyfile(out / f, dest / (f + ".tmp"))
            (dest / (f + ".tmp")).replace(dest / f)
    print(json.dumps({"tower": str(out / T.TOWER_FILE), "bytes": card["bytes"], "sha256": card["sha256"]}))
    return 0


if __name__ == "__main__":
    cli_main(main, __doc__)
