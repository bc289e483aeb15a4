"""Vision-tower pretraining on simulator state: the Qwen3-VL vision tower and merger learn what each frame shows.

A from-scratch tower given one Yes/No per grid memorises the wide world (docs/EXPERIMENTS.md). The simulator
gives far more for free: for every frame of every view, the state (an object held, lifted, tipped, at its place,
the door open, liquid in its vessel, the hand moving, every goal holding, a failure so far) and where the gripper,
the task objects and their places are in the picture (labrobfail_data/frame_targets.py, from simulator state only).
Here the tower sees the same 512 x 512 keyframe grids the VQA model sees (16 cells of 128 px = 4 x 4 merged tokens
each), augmented per view (labrobfail_vlm/augment.py), and a training-only head reads every target from the merged
tokens the decoder will receive:

    cell targets   each token -> MLP -> K scores; a cell's K logits = the mean over its 16 tokens + a bias
    token targets  each token -> MLP -> C scores: is the gripper / a task object / a goal place in this token?

so the evidence must sit in single tokens, which is what a small decoder reads (docs/EXPERIMENTS.md, 2026-11-22
"The decoder reads the tower once ..."). The head is thrown away; the tower and merger are exported (`export`)
as `tower.safetensors` plus a card (`tower.json`: config, data, held-out accuracy per target, command, sha256),
which labrobfail_vlm/model/tower.py loads into the tiny Qwen3-VL."""

from __future__ import annotations

import io
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Collection, Sequence

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from PIL import Image

from labrobfail_vlm.augment import Augment, augment_views
from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.grid import GridConfig, build_grid
from labrobfail_vlm.io import sha256_file
from labrobfail_vlm.train.grounding import TOKEN_PX, cell_gather, merged_tokens

TOWER_FILE, CARD_FILE, CARD_MD = "tower.safetensors", "tower.json", "TOWER_CARD.md"


# ---- data -----------------------------------------------------------------------------------------------------
@dataclass
class Sample:
    grid: Image.Image
    cells: np.ndarray  # (max_frames * views, K): 1 / 0, -1 = no target (not applicable, or a blank cell)
    tokens: np.ndarray  # (max_frames * views, tokens per cell, C): 1 / 0, -1 = unknown (no camera matrices)


class TowerData:
    """The trajectories of a tower dataset (labrobfail_data/tower_data.py) in the chosen splits and variants, in memory
    as PNG bytes plus targets; `sample` composes one grid in a layout (view names), augmented or not."""

    def __init__(
        self,
        data_dir: str | Path,
        splits: Collection[str] = (),
        variants: Collection[str] = (),
        limit: int | None = None,
    ):
        import pyarrow.parquet as pq

        d = Path(data_dir)
        try:
            index = json.loads((d / "index.json").read_text())
        except (OSError, ValueError):
            raise ConfigError(
                f"data: {d} has no readable index.json (build it with labrobfail-build-tower-data)"
            ) from None
        self.cell_names, self.token_names = list(index["cell_targets"]), list(index["token_targets"])
        self.image_size, p = int(index["image_size"]), int(index["max_points"])
        k, c = len(self.cell_names), len(self.token_names)
        self.rows: list[dict[str, Any]] = []
        for name in index["files"]:
            for r in pq.read_table(d / name).to_pylist():
                split = index["split"][r["group"]]
                if (splits and split not in splits) or (variants and r["variant"] not in variants):
                    continue
                f, v = int(r["frames"]), len(r["views"])
                r["cells"] = np.frombuffer(r["cells"], np.float32).reshape(f, v, k)
                r["points"] = np.frombuffer(r["points"], np.float32).reshape(f, v, c, p, 2)
                r["split"] = split
                self.rows.append(r)
                if limit is not None and len(self.rows) >= limit:
                    return

    def __len__(self) -> int:
        return len(self.rows)

    def sample(self, i: int, layout: Sequence[str], grid: GridConfig, aug: Augment | None = None) -> Sample:
        r = self.rows[i]
        try:
            vi = [r["views"].index(v) for v in layout]
        except ValueError:
            raise ConfigError(
                f"layouts: trajectory {r['trajectory']} has views {r['views']}, not {list(layout)} "
                "(generate with backend_kwargs.wrist=true for a wrist layout)"
            ) from None
        frames = [[np.asarray(Image.open(io.BytesIO(b)).convert("RGB")) for b in r["images"][v]] for v in vi]
        img = build_grid(augment_views(frames, aug), grid)
        nv, nf = len(vi), int(r["frames"])
        rows, cols = grid.shape(nv)
        cell_px = min(grid.width // cols, grid.height // rows)
        side = cell_px // TOKEN_PX
        size = (self.image_size, self.image_size)
        cells = np.full((grid.max_frames * nv, len(self.cell_names)), -1.0, np.float32)
        tokens = np.full((grid.max_frames * nv, side * side, len(self.token_names)), -1.0, np.float32)
        for t in range(nf):
            for k, v in enumerate(vi):
                cells[t * nv + k] = r["cells"][t, v]
                pts = r["points"][t, v]  # (C, P, 2)
                if np.isnan(pts[0]).all():  # no gripper position: this view's camera was not recorded
                    continue
                if aug is not None:
                    pts = aug.points(pts.astype(np.float64), k, size)
                tokens[t * nv + k] = token_map(pts, self.image_size, side)
        return Sample(img, cells, tokens)


def token_map(points: np.ndarray, image_size: int, side: int) -> np.ndarray:
    """(C, P, 2) pixel positions -> (side * side, C): 1 for each token a point of that channel falls into."""
    out = np.zeros((side * side, points.shape[0]), np.float32)
    for c, pts in enumerate(points):
        for x, y in pts:
            if np.isfinite(x) and np.isfinite(y) and 0 <= x < image_size and 0 <= y < image_size:
                out[int(y * side / image_size) * side + int(x * side / image_size), c] = 1.0
    return out


def collate(samples: Sequence[Sample], image_processor: Any) -> dict[str, torch.Tensor]:
    px = image_processor(images=[s.grid for s in samples], return_tensors="pt")
    return {
        "pixel_values": px["pixel_values"],
        "image_grid_thw": px["image_grid_thw"],
        "cells": torch.from_numpy(np.stack([s.cells for s in samples])),
        "tokens": torch.from_numpy(np.stack([s.tokens for s in samples])),
    }


# ---- model ----------------------------------------------------------------------------------------------------
def vision_config(vision: dict[str, Any], out_hidden_size: int) -> Any:
    """The tower's Qwen3VLVisionConfig: the tiny preset's defaults, `vision` over them."""
    from transformers.models.qwen3_vl.configuration_qwen3_vl import Qwen3VLVisionConfig

    from labrobfail_vlm.model.tiny import TINY_VISION

    return Qwen3VLVisionConfig(**{**TINY_VISION, **dict(vision), "out_hidden_size": int(out_hidden_size)})


def build_tower(vision: dict[str, Any], out_hidden_size: int, seed: int = 0) -> nn.Module:
    from transformers.models.qwen3_vl.modeling_qwen3_vl import Qwen3VLVisionModel

    torch.manual_seed(seed)
    return Qwen3VLVisionModel._from_config(vision_config(vision, out_hidden_size))


class TowerHeads(nn.Module):
    """Training-only readout: each merged token -> K cell scores (averaged over the cell) and C token scores."""

    def __init__(self, dim: int, k: int, c: int, hidden: int = 256):
        super().__init__()
        self.k = k
        self.mlp = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, k + c))
        self.bias = nn.Parameter(torch.zeros(k))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x: (cells, tokens per cell, dim) -> cell logits (cells, K), token logits (cells, tokens, C)."""
        z = self.mlp(x.float())
        return z[..., : self.k].mean(1) + self.bias, z[..., self.k :]


def readout(
    tower: nn.Module, heads: TowerHeads, batch: dict[str, torch.Tensor], grid: GridConfig, views: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Cell logits (B, cells, K) and token logits (B, cells, T, C) of a batch of grids."""
    tok = merged_tokens(tower(batch["pixel_values"], grid_thw=batch["image_grid_thw"]))
    cells, toks, at = [], [], 0
    for t, h, w in batch["image_grid_thw"].tolist():
        n = t * (h // 2) * (w // 2)
        idx = cell_gather(grid, views, h // 2, w // 2).to(tok.device)
        c, k = heads(tok[at : at + n][idx])
        cells.append(c)
        toks.append(k)
        at += n
    return torch.stack(cells), torch.stack(toks)


def positive_weights(data: "TowerData", cap: float = 10.0) -> torch.Tensor:
    """Per cell target, negatives / positives over the training cells where it applies (1 to `cap`): a rare
    event (a vessel tipped, liquid spilled) then weighs as much as its absence instead of being never predicted."""
    y = np.concatenate([r["cells"].reshape(-1, len(data.cell_names)) for r in data.rows])
    pos, neg = (y > 0.5).sum(0), ((y >= 0) & (y < 0.5)).sum(0)
    return torch.tensor(np.clip(neg / np.maximum(pos, 1), 1.0, cap), dtype=torch.float32)


def tower_loss(
    zc: torch.Tensor,
    zt: torch.Tensor,
    batch: dict[str, torch.Tensor],
    token_weight: float,
    pos_weight: float,
    cell_pos_weight: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Masked BCE over the cell targets (positives of target k weighted `cell_pos_weight[k]`) plus `token_weight`
    x masked BCE over the token targets (positives weighted `pos_weight`: a point fills one token of a cell's 16)."""
    yc, yt = batch["cells"], batch["tokens"]
    mc, mt = yc >= 0, yt >= 0
    w = None if cell_pos_weight is None else cell_pos_weight.expand_as(yc)[mc]
    lc = F.binary_cross_entropy_with_logits(zc[mc], yc[mc], pos_weight=w) if mc.any() else zc.sum() * 0
    pw = torch.tensor(float(pos_weight))
    lt = F.binary_cross_entropy_with_logits(zt[mt], yt[mt], pos_weight=pw) if mt.any() else zt.sum() * 0
    return lc + token_weight * lt, {"cell": float(lc.detach()), "token": float(lt.detach())}


# ---- evaluation -----------------------------------------------------------------------------------------------
@torch.no_grad()
def evaluate(
    tower: nn.Module,
    heads: TowerHeads,
    data: TowerData,
    layout: Sequence[str],
    grid: GridConfig,
    image_processor: Any,
    batch_size: int = 8,
) -> dict[str, Any]:
    """Held-out accuracy of every target (no augmentation): per cell target, accuracy, balanced accuracy (mean of
    the recall of each class) and the positive rate over the cells where it applies; per token target, how often
    the top-scoring token of a cell holds the point (cells that show one) against chance (points per token);
    `detection`: the last shown frame's failed_by_now (views averaged) against the trajectory's label."""
    was = tower.training, heads.training
    tower.eval()
    heads.eval()
    zc_all, yc_all, zt_all, yt_all = [], [], [], []
    for s in range(0, len(data), batch_size):
        b = collate([data.sample(i, layout, grid) for i in range(s, min(s + batch_size, len(data)))], image_processor)
        zc, zt = readout(tower, heads, b, grid, len(layout))
        zc_all.append(zc)
        yc_all.append(b["cells"])
        zt_all.append(zt)
        yt_all.append(b["tokens"])
    tower.train(was[0])
    heads.train(was[1])
    zc, yc, zt, yt = (torch.cat(x) for x in (zc_all, yc_all, zt_all, yt_all))
    out: dict[str, Any] = {"trajectories": len(data), "layout": list(layout), "cells": {}, "tokens": {}}
    for k, name in enumerate(data.cell_names):
        m = yc[..., k] >= 0
        y, p = yc[..., k][m] > 0.5, zc[..., k][m] > 0
        if not m.any():
            continue
        rec = [float((p[y == c] == c).float().mean()) for c in (True, False) if (y == c).any()]
        out["cells"][name] = {
            "accuracy": round(float((p == y).float().mean()), 4),
            "balanced": round(sum(rec) / len(rec), 4),
            "positive": round(float(y.float().mean()), 4),
            "n": int(m.sum()),
        }
    for c, name in enumerate(data.token_names):
        y = yt[..., c]
        has = (y > 0.5).any(-1) & (y >= 0).all(-1)
        if not has.any():
            continue
        top = zt[..., c].argmax(-1, keepdim=True)
        hit = y.gather(-1, top).squeeze(-1)[has] > 0.5
        out["tokens"][name] = {
            "top1": round(float(hit.float().mean()), 4),
            "chance": round(float((y[has] > 0.5).float().mean()), 4),
            "n": int(has.sum()),
        }
    if "failed_by_now" in data.cell_names:
        k, nv = data.cell_names.index("failed_by_now"), len(layout)
        last = [int(r["frames"]) - 1 for r in data.rows]
        z = torch.stack([zc[i, t * nv : (t + 1) * nv, k].mean() for i, t in enumerate(last)])
        y = torch.tensor([not r["success"] for r in data.rows])
        out["detection"] = {
            "accuracy": round(float(((z > 0) == y).float().mean()), 4),
            "majority": round(max(float(y.float().mean()), 1 - float(y.float().mean())), 4),
            "n": len(data.rows),
        }
    return out


# ---- export ---------------------------------------------------------------------------------------------------
def export(tower: nn.Module, out: Path, card: dict[str, Any]) -> dict[str, Any]:
    """tower.safetensors (the vision tower and merger, float32, keys as in `model.visual`) and tower.json."""
    from safetensors.torch import save

    from labrobfail_vlm.io import atomic_write_bytes, atomic_write_json

    out.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(
        out / TOWER_FILE, save({k: v.detach().float().contiguous() for k, v in tower.state_dict().items()})
    )
    card = {
        **card,
        "file": TOWER_FILE,
        "bytes": (out / TOWER_FILE).stat().st_size,
        "parameters": sum(p.numel() for p in tower.parameters()),
        "sha256": sha256_file(out / TOWER_FILE),
    }
    atomic_write_json(out / CARD_FILE, card)
    return card


def lr_at(step: int, total: int, warmup: int, lr: float) -> float:
    """Linear warm-up, then cosine decay to zero."""
    if step < warmup:
        return lr * (step + 1) / max(1, warmup)
    return lr * 0.5 * (1 + math.cos(math.pi * (step - warmup) / max(1, total - warmup)))


def clock() -> tuple[float, float]:
    return time.perf_counter(), time.process_time()
