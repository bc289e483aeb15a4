"""Frame grounding: a training-only head that teaches the vision tower where a failure shows.

Trained from scratch, the VLM gets one Yes/No per grid for Q2, and that signal must travel through two decoder
layers and the merger before it reaches the vision tower; the model settles on text priors instead (see
docs/EXPERIMENTS.md, 2026-11-22 "From-scratch recipe, lever by lever"). The simulator says more for free: the
grid frame where the failure first shows (the labeler's failure keyframe, from simulator state). So every cell
of the grid gets a target, "has the trajectory failed by this frame?" (0 before that frame and in successes, 1
from it on, none for cells the grid leaves blank), and a small head reads it from the visual tokens the language
model receives (the merger's output). Two heads (`grounding.head`):

    token: each token -> MLP -> one score; a cell's mean score + a per-cell bias; the time step's views summed
    cell:  a cell's tokens (flattened) -> MLP -> + time/view embedding -> the time step's views -> one logit

The `token` head is the default because it asks for what a small decoder can read: its first layer's MLP
works on one token at a time and its attention then averages tokens, so the evidence must sit in single
tokens. The `cell` head reads combinations of a cell's tokens; it learns faster, but the decoder cannot use
what it learns (docs/EXPERIMENTS.md, 2026-11-22 "The decoder reads the tower once ...").

Its loss is the mean binary cross-entropy over shown cells, plus a ranking term for success/failure twins in
the same batch (same scene, camera and distractors; only the failure differs): the failed twin's last frame
must score above the successful one's. The head adds `grounding.weight` x that loss to the VQA loss; it is
not part of the model (checkpoints keep it beside the weights, `GROUNDING_FILE`, only for resuming), and the
benchmark never sees it.

`pretrain` is stage A of the from-scratch recipe (`grounding.pretrain_epochs`): the vision tower and head alone
learn the frame targets before any question is asked (vision forward only, so an epoch costs a fraction of a
VQA epoch); the VQA training then starts from a tower whose tokens already show failures.
"""

from __future__ import annotations

import math
from functools import lru_cache
from pathlib import Path
from typing import Any

import torch
import torch.nn as nn
import torch.nn.functional as F

from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.grid import GridConfig

GROUNDING_FILE = "grounding_head.safetensors"
TOKEN_PX = 32  # Qwen3-VL: 16 px patches merged 2x2


def frame_targets(meta: dict[str, Any], max_frames: int) -> list[float]:
    """Per grid frame 1..max_frames: 1.0 once the failure shows, 0.0 before it (and in a success), -1.0 where
    the grid shows nothing (past the trajectory's frames, or past a prefix grid's cut)."""
    shown = min(int(meta.get("visible") or meta["frames"]), int(meta["frames"]))
    fail_at = math.inf if meta["success"] else int(meta["frame"])
    return [-1.0 if t > shown else float(t >= fail_at) for t in range(1, max_frames + 1)]


def dataset_targets(trajectories: list[dict[str, Any]], grid: GridConfig) -> tuple[dict[str, list[float]], int]:
    """trajectory -> frame targets, and the dataset's number of camera views (every grid must have the same)."""
    views = {t.get("views") for t in trajectories}
    if len(views) != 1 or None in views:
        raise ConfigError(
            "grounding: the dataset's trajectories.json lacks one common 'views' count (built before "
            "grounding existed); rebuild it with labrobfail-build-dataset"
        )
    return {t["trajectory"]: frame_targets(t, grid.max_frames) for t in trajectories}, int(views.pop())


def cell_index(grid: GridConfig, views: int, h_tok: int, w_tok: int) -> torch.Tensor:
    """(h_tok * w_tok,) raster order of merged tokens -> time step t (0-based) of the cell under the token's
    centre, times `views` plus the view; -1 for tokens outside every cell."""
    rows, cols = grid.shape(views)
    cw, ch = grid.width // cols, grid.height // rows
    sx, sy = grid.width / (w_tok * TOKEN_PX), grid.height / (h_tok * TOKEN_PX)  # the processor may resize
    lookup = {grid.cell(t, k, views): t * views + k for t in range(grid.max_frames) for k in range(views)}
    out = torch.full((h_tok * w_tok,), -1, dtype=torch.long)
    for i in range(h_tok):
        for j in range(w_tok):
            y, x = (i + 0.5) * TOKEN_PX * sy, (j + 0.5) * TOKEN_PX * sx
            out[i * w_tok + j] = lookup.get((int(y // ch), int(x // cw)), -1)
    return out


@lru_cache(maxsize=64)
def cell_gather(grid: GridConfig, views: int, h_tok: int, w_tok: int) -> torch.Tensor:
    """(cells, tokens per cell) indices of the merged tokens of a grid image, cell = t * views + view, each cell's
    tokens in raster order; every cell must cover the same number of tokens (cells of multiples of 32 px)."""
    idx = cell_index(grid, views, h_tok, w_tok)
    cells = grid.max_frames * views
    counts = torch.bincount(idx[idx >= 0], minlength=cells)
    if counts.min() != counts.max() or counts.min() == 0:
        raise ConfigError(
            f"grounding: grid cells cover unequal numbers of visual tokens ({counts.tolist()}); "
            "use a grid whose cells are multiples of 32 px"
        )
    order = torch.argsort(idx * (h_tok * w_tok) + torch.arange(h_tok * w_tok))  # by cell, then raster
    return order[int((idx < 0).sum()) :].view(cells, int(counts[0]))


HEADS = ("token", "cell")


class _CellHead(nn.Module):
    """Visual tokens of one grid -> one logit per time step (subclasses say how a cell's tokens are read)."""

    def __init__(self, grid: GridConfig, views: int):
        super().__init__()
        self.grid, self.views = grid, int(views)
        self.cells = grid.max_frames * self.views

    def gather(self, h_tok: int, w_tok: int) -> torch.Tensor:
        """(cells, tokens per cell) token indices; every cell of a grid covers the same number of tokens."""
        return cell_gather(self.grid, self.views, h_tok, w_tok)

    def cell_tokens(self, tokens: torch.Tensor, h_tok: int, w_tok: int) -> torch.Tensor:
        """(cells, tokens per cell, dim) in float: each cell's tokens of one grid, cell = t * views + k."""
        return tokens.float()[self.gather(h_tok, w_tok).to(tokens.device)]


class TokenHead(_CellHead):
    """Each token through a small MLP to one score; a cell scores the mean of its tokens plus its own bias, a
    time step the sum of its views' cells."""

    def __init__(self, dim: int, grid: GridConfig, views: int, hidden: int = 64):
        super().__init__(grid, views)
        self.token = nn.Sequential(nn.Linear(int(dim), hidden), nn.GELU(), nn.Linear(hidden, 1))
        self.bias = nn.Parameter(torch.zeros(self.cells))

    def forward(self, tokens: torch.Tensor, h_tok: int, w_tok: int) -> torch.Tensor:
        c = self.token(self.cell_tokens(tokens, h_tok, w_tok)).squeeze(-1).mean(1) + self.bias  # (cells,)
        return c.view(self.grid.max_frames, self.views).sum(1)


class CellHead(_CellHead):
    """Each cell's tokens, flattened in raster order, through a small MLP (with the cell's time/view
    embedding), the views of a time step concatenated."""

    def __init__(self, dim: int, grid: GridConfig, views: int, hidden: int = 64):
        super().__init__(grid, views)
        # the grid's own token layout sizes the cell MLP (the processor keeps sides that are multiples of 32 px)
        per_cell = self.gather(round(grid.height / TOKEN_PX), round(grid.width / TOKEN_PX)).shape[1]
        self.cell = nn.Sequential(nn.Linear(int(dim) * per_cell, 4 * hidden), nn.GELU(), nn.Linear(4 * hidden, hidden))
        self.pos = nn.Parameter(torch.zeros(self.cells, hidden))
        self.out = nn.Linear(hidden * self.views, 1)

    def forward(self, tokens: torch.Tensor, h_tok: int, w_tok: int) -> torch.Tensor:
        e = self.cell(self.cell_tokens(tokens, h_tok, w_tok).flatten(1)) + self.pos  # (cells, hidden)
        return self.out(e.view(self.grid.max_frames, -1)).squeeze(-1)


def check_head(kind: str) -> str:
    if kind not in HEADS:
        raise ConfigError(f"grounding.head: expected one of {', '.join(HEADS)}, got {kind!r}")
    return kind


def make_head(kind: str, dim: int, grid: GridConfig, views: int) -> _CellHead:
    return (TokenHead if check_head(kind) == "token" else CellHead)(dim, grid, views)


def grounding_loss(
    head: _CellHead,
    tokens: torch.Tensor,
    thw: torch.Tensor,
    targets: torch.Tensor,
    groups: torch.Tensor | None = None,
    rank: float = 1.0,
) -> torch.Tensor:
    """`tokens`: the merger's output for the batch's images, concatenated; `thw`: image_grid_thw (B, 3);
    `targets`: (B, max_frames) from `frame_targets`; `groups`: (B,) pair ids (twins share one)."""
    logits, at = [], 0
    for t, h, w in thw.tolist():
        n = t * (h // 2) * (w // 2)
        logits.append(head(tokens[at : at + n], h // 2, w // 2))
        at += n
    z = torch.stack(logits)
    y = targets.to(z.device)
    shown = y >= 0
    loss = F.binary_cross_entropy_with_logits(z[shown], y[shown])
    if rank and groups is not None:
        last = shown.long().cumsum(1).argmax(1)  # the last shown frame
        zl = z.gather(1, last[:, None]).squeeze(1)
        failed = y.gather(1, last[:, None]).squeeze(1) > 0.5
        g = groups.to(z.device)
        twins = (g[:, None] == g[None, :]) & failed[:, None] & ~failed[None, :]  # (failed i, successful j)
        if twins.any():
            fi, sj = twins.nonzero(as_tuple=True)
            loss = loss + rank * F.softplus(zl[sj] - zl[fi]).mean()
    return loss


def vision_module(model: nn.Module) -> nn.Module:
    """The vision tower inside a Qwen3-VL model (under a PeftModel too)."""
    for name, m in model.named_modules():
        if name.endswith("visual") and hasattr(m, "merger"):
            return m
    raise ConfigError("grounding: the model has no Qwen3-VL vision tower (a module named *visual with a merger)")


def merged_tokens(output: Any) -> torch.Tensor:
    """The merger's tokens (what the decoder receives) from a vision tower's forward output."""
    return output.pooler_output if hasattr(output, "pooler_output") else output[1]


class TokenTap:
    """Keeps the vision tower's last merged tokens (its pooler_output) from each forward pass."""

    def __init__(self, model: nn.Module):
        self.tokens: torch.Tensor | None = None
        self.handle = vision_module(model).register_forward_hook(self._hook)

    def _hook(self, module: nn.Module, args: Any, output: Any) -> None:
        self.tokens = merged_tokens(output)

    def take(self) -> torch.Tensor:
        if self.tokens is None:
            raise RuntimeError("grounding: the vision tower did not run in this forward pass")
        t, self.tokens = self.tokens, None
        return t


def save_head(head: _CellHead, out: Path) -> None:
    from safetensors.torch import save_file

    save_file({k: v.detach().cpu().contiguous() for k, v in head.state_dict().items()}, str(out / GROUNDING_FILE))


def load_head(head: _CellHead, ckpt: Path) -> bool:
    """Restore the head saved beside a checkpoint (resume); False when the checkpoint has none."""
    from safetensors.torch import load_file

    path = Path(ckpt) / GROUNDING_FILE
    if not path.is_file():
        return False
    head.load_state_dict(load_file(str(path)))
    return True


STAGE_A_DIR = "stage_a"  # under output_dir: epoch-N/ after each stage-A epoch (the newest complete one kept)
STAGE_A_STATE = "state.json"  # written last into epoch-N


def stage_a_state(output_dir: str | Path) -> Path | None:
    """Where a killed stage A left off, or None (train.py resume=true goes on from it)."""
    from labrobfail_vlm.io import newest_complete

    return newest_complete(Path(output_dir) / STAGE_A_DIR, "epoch", STAGE_A_STATE)


def _save_stage_a(root: Path, epoch: int, vm: nn.Module, head: nn.Module, opt: Any, sched: Any, meta: dict) -> None:
    """One epoch's state, complete only once its state.json lands; then older epochs go. Weights as safetensors,
    the optimizer, schedule and torch RNG beside them (labrobfail_vlm.io.save_resume_state)."""
    import shutil

    from safetensors.torch import save_file

    from labrobfail_vlm.io import save_resume_state

    d = root / f"epoch-{epoch}"
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)
    save_file({k: v.detach().cpu().contiguous() for k, v in vm.state_dict().items()}, str(d / "tower.safetensors"))
    save_head(head, d)
    tensors = {"opt": opt.state_dict(), "sched": sched.state_dict(), "rng": torch.get_rng_state()}
    save_resume_state(d, tensors, meta, STAGE_A_STATE)
    for old in root.glob("epoch-*"):
        if old != d:
            shutil.rmtree(old, ignore_errors=True)


def pretrain(
    model: nn.Module,
    head: _CellHead,
    batches: Any,
    epochs: int,
    lr: float,
    rank: float = 1.0,
    progress: bool = True,
    state_dir: Path | None = None,
    resume: bool = False,
    augment: Any = None,
) -> dict[str, float]:
    """Stage A: the vision tower (and its merger) with the head on the frame targets alone, `epochs` passes over
    `batches` (the training dataloader: collated batches with pixel_values, image_grid_thw, frame_target,
    pair_group), one AdamW at the head's rate `lr` with a linear warm-up and cosine decay (the VQA stage that
    follows keeps its own per-group rates). Returns the mean grounding loss of the first and the last epoch.

    With `state_dir`, the state after each epoch is saved there (STAGE_A_DIR/epoch-N); with `resume`, the run goes
    on after the newest one: weights, optimizer, schedule, the torch RNG and the data order (the dataloader's epoch);
    the grid augmentation (`augment`, a GridAugment) draws by pass and pair, so a killed run ends as an uninterrupted
    one would."""
    from safetensors.torch import load_file
    from tqdm.auto import tqdm
    from transformers import get_cosine_schedule_with_warmup

    from labrobfail_vlm.io import load_resume_state

    vm = vision_module(model)
    params = [p for p in vm.parameters() if p.requires_grad] + list(head.parameters())
    opt = torch.optim.AdamW(params, lr=float(lr))
    total = int(epochs) * len(batches)
    sched = get_cosine_schedule_with_warmup(opt, max(1, total // 10), total)
    means: list[float] = []
    start = 0
    root = Path(state_dir) / STAGE_A_DIR if state_dir is not None else None
    last = stage_a_state(state_dir) if state_dir is not None and resume else None
    if last is not None:
        state, meta = load_resume_state(last, STAGE_A_STATE)
        if meta["epochs"] != int(epochs) or meta["batches"] != len(batches):
            raise ConfigError(
                f"resume: {last} is from a stage A of {meta['epochs']} epochs x {meta['batches']} batches, not "
                f"{int(epochs)} x {len(batches)}; rerun without resume=true to start over"
            )
        vm.load_state_dict(load_file(str(last / "tower.safetensors")))
        load_head(head, last)
        opt.load_state_dict(state["opt"])
        sched.load_state_dict(state["sched"])
        torch.set_rng_state(state["rng"])
        start, means = int(meta["epoch"]), list(meta["means"])
        if hasattr(batches, "iteration"):  # accelerate's loader: its pass count is the sampler's epoch
            batches.iteration = start
    was = vm.training
    vm.train()
    bar = tqdm(total=total, initial=start * len(batches), desc="grounding pre-training", disable=not progress)
    for epoch in range(start, int(epochs)):
        if augment is not None:
            augment.epoch = (0, epoch)
        losses = []
        for b in batches:
            tokens = merged_tokens(vm(b["pixel_values"], grid_thw=b["image_grid_thw"]))
            loss = grounding_loss(head, tokens, b["image_grid_thw"], b["frame_target"], b["pair_group"], rank)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, 1.0)
            opt.step()
            sched.step()
            opt.zero_grad(set_to_none=True)
            losses.append(float(loss.detach()))
            bar.update(1)
            bar.set_postfix(loss=f"{losses[-1]:.3f}")
        means.append(sum(losses) / max(1, len(losses)))
        if root is not None:
            meta = {"epoch": epoch + 1, "epochs": int(epochs), "batches": len(batches), "means": means}
            _save_stage_a(root, epoch + 1, vm, head, opt, sched, meta)
    bar.close()
    vm.train(was)
    if not means:
        return {}
    out = {"first_epoch_loss": round(means[0], 4), "last_epoch_loss": round(means[-1], 4)}
    return out | ({"resumed_at_epoch": start} if start else {})
