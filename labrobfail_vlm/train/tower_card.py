"""The tower's card: TOWER_CARD.md and the data of tower.json (what the tower is, what it learned from, how well it
reads each target held out). Written by `labrobfail-pretrain-tower` (labrobfail_vlm/train/pretrain_tower.py)."""

from __future__ import annotations

import json
import shlex
from pathlib import Path
from typing import Any

from labrobfail_vlm import drawing
from labrobfail_vlm.train import tower as T

TRAINING_KEYS = (
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


def shard_origin(shard_dir: str) -> str:
    """How a shard folder was generated (its run.json), in words for the card: the variant, seed, any scene family
    other than the variant's own (so a reader sees which frames were domain-randomised), a lit button lamp and broken
    glass drawn."""
    try:
        run = json.loads((Path(shard_dir) / "run.json").read_text())
    except (OSError, ValueError):
        return shard_dir
    kw, drawn = run.get("backend_kwargs") or {}, drawing.of_run(run) or {}
    extra = (
        (f", scene family {kw['scene_family']}" if kw.get("scene_family") else "")
        + (", button lamp on" if drawn.get("button_lamp") else "")
        + (", broken glass drawn" if drawn.get("broken_glass") else "")
    )
    return f"{shard_dir} ({run.get('variant')}, seed {run.get('seed')}{extra})"


def _row(name: str, cells: list[dict[str, float] | None], fmt: str) -> str:
    """One table row: the target's name, then each held-out set's figures (– where the set lacks the target)."""
    return f"| {name} | " + " | ".join("–" if c is None else fmt.format(**c) for c in cells) + " |"


def augment_line(section: dict[str, Any]) -> str:
    """What the tower's training augmentation did to each grid, read from its card (a card older than the
    `raise_saturation` key was trained raising saturation)."""
    from labrobfail_vlm.augment import AugmentConfig

    if not section:
        return "Augmentation: not recorded on this card."
    a = AugmentConfig.from_section({"hue": None, **section})
    sat = (
        "contrast and saturation gains could raise a pixel's saturation (into the sealed scene family's range)"
        if a.raise_saturation
        else "no pixel's saturation raised above what was rendered"
    )
    return (
        f"Augmentation per grid: each view shifted up to {a.shift_px:g} px and zoomed by up to {a.scale:g}; "
        f"brightness, contrast and saturation factors in [{1 - a.colour:g}, {1 + a.colour:g}], hue turned up to "
        f"{a.hue_turns:g} turn; {sat}."
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
        "Per frame and view, from simulator state (labrobfail_data/frame_targets.py): "
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
        cell = "{balanced:.3f} (pos {positive:.2f})"
        lines += [_row(t, [s["cells"].get(t) for s in sets.values()], cell) for t in first["cells"]]
        token = "{top1:.3f} (chance {chance:.2f})"
        lines += [_row(f"position: {t}", [s["tokens"].get(t) for s in sets.values()], token) for t in first["tokens"]]
        det = [s.get("detection") for s in sets.values()]
        lines.append(_row("detection (last frame, failed_by_now)", det, "{accuracy:.3f} (majority {majority:.3f})"))
        lines.append("")
    lines += [
        "## Use",
        "",
        card["use"],
        "",
        "## Reproduce",
        "",
        augment_line(card["training"].get("augment") or {}),
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


def card_data(
    cfg: Any,
    argv: list[str],
    train: T.TowerData,
    evals: dict[str, T.TowerData],
    heldout: dict[str, Any],
    state: dict[str, Any],
    init_sha: str | None,
) -> dict[str, Any]:
    """tower.json's fields before export adds the file's size and sha256."""
    from omegaconf import OmegaConf

    vision = OmegaConf.to_container(cfg.vision)
    index = json.loads((Path(cfg.data.out_dir) / "index.json").read_text())
    frames = sum(int(r["frames"]) * len(r["views"]) for r in train.rows)
    views = sorted({v for r in train.rows for v in r["views"]})
    return {
        "vision_config": T.vision_config(vision, int(cfg.out_hidden_size)).to_dict(),
        "out_hidden_size": int(cfg.out_hidden_size),
        "grid": dict(cfg.grid),
        "layouts": [list(lay) for lay in cfg.layouts],
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
            f"{len(train):,} seen training trajectories ({frames:,} view-frames of {index['image_size']} px, views "
            f"{views}) from {', '.join(shard_origin(s) for s in index['shards'])}; held out: "
            + ", ".join(f"{k} {len(d)}" for k, d in evals.items())
            + " trajectories."
        ),
        "training": {k: cfg[k] for k in TRAINING_KEYS}
        | {"augment": dict(cfg.augment), "init_sha256": init_sha, "wall_s": state["wall_s"], "cpu_s": state["cpu_s"]},
        "heldout": heldout,
        "use": (
            "The tiny Qwen3-VL of `preset=tiny` (train.py) takes this tower and merger in place of its random "
            "ones (`tower=shipped`, the default; `tower=scratch` or a folder holding tower.safetensors + "
            "tower.json). A real Qwen3-VL keeps its own pretrained tower: its card's targets are a recipe "
            "for sim-specific pretraining of that tower (same data, same heads) before the hybrid fine-tune."
        ),
        "command": " ".join(shlex.quote(a) for a in ["labrobfail-pretrain-tower", *argv]),
    }
