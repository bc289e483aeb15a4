"""Encode each training grid once when the vision tower is frozen.

With the tower and merger frozen (`tower=shipped`: `lr.vision=0 lr.merger=0`) the tower is a fixed function of
the pixels, yet the Trainer runs it again on every grid in every epoch; in the tiny recipe that forward pass is
about half of each training step (docs/EXPERIMENTS.md, 2026-11-27 "Encoding each grid once ..."). `TowerCache`
takes the place of the tower's `forward`: each image's output (the merged tokens and any DeepStack features) is
kept under a digest of its patches and grid size (or of its file: below) and served again on the next epoch.

Why per image, and why by content:
- A miss is encoded alone, never beside the other images of its batch, so a stored value does not depend on
  which images happened to share a batch: a resumed run, or one with another batch size, reads the same numbers.
- The key is the pixels themselves (or the file they were read from, which the key's modification time pins), so
  a stale value cannot be served: an augmented grid is simply a miss.
- The tower has no dropout (Qwen3-VL's vision attention runs at p = 0), so train and eval mode give one output.
Memory is bounded by `max_mb`; once full, further images are encoded every time as before.

Keyed by file: reading, preprocessing and hashing a 512x512 grid cost about a fifth of a later epoch's step
(docs/EXPERIMENTS.md, 2026-12-01 late night, "Grids keyed by file ..."). When nothing augments the grids, the
collator names each grid by its file (`file_key`: path, size, modification time) and hands those keys over
(`given`) with the batch; a grid stored under its file key is then neither read nor preprocessed again, and its
rows of `pixel_values` are zeros that nothing reads. A stored value never leaves the store, so a key the collator
saw stored is still there when the batch runs.
"""

from __future__ import annotations

import hashlib
import os
from typing import Any

import torch
from torch import nn


class TowerCache:
    """Replaces `visual.forward` on one frozen Qwen3-VL vision tower (see the module docstring)."""

    def __init__(self, visual: nn.Module, max_mb: float):
        if any(p.requires_grad for p in visual.parameters()):
            raise ValueError("TowerCache: the vision tower trains; its outputs change every step")
        self.encode = visual.forward  # the bound original, decorators included
        self.max_bytes, self.bytes = int(max_mb * 2**20), 0
        self.store: dict[bytes, tuple[torch.Tensor, list[torch.Tensor]]] = {}
        self.hits = self.misses = 0
        self.visual, self.weights = visual, None  # the tower, and a digest of its weights once asked for
        self.given: list[bytes] | None = None  # file keys of the next call's images, set by the trainer
        visual.forward = self  # an instance attribute: nn.Module.__call__ (and its hooks) now call this

    def weights_digest(self) -> bytes:
        """A digest of the tower's weights (computed once: a cached tower does not train)."""
        if self.weights is None:
            h = hashlib.blake2b(digest_size=16)
            for name, t in sorted(self.visual.state_dict().items()):
                h.update(name.encode())
                h.update(t.detach().contiguous().view(torch.uint8).cpu().numpy())
            self.weights = h.digest()
        return self.weights

    def stats(self) -> dict[str, float]:
        return {"hits": self.hits, "misses": self.misses, "stored": len(self.store), "mb": round(self.bytes / 2**20, 1)}

    def __contains__(self, key: bytes) -> bool:
        return key in self.store

    @staticmethod
    def pixel_key(pixels: torch.Tensor, thw: torch.Tensor) -> bytes:
        h = hashlib.blake2b(digest_size=16)
        h.update(str((pixels.dtype, tuple(pixels.shape), thw.tolist())).encode())
        # the raw bytes (bfloat16 has no numpy dtype), read in place by the buffer protocol: no copy per grid
        h.update(pixels.detach().contiguous().view(torch.uint8).cpu().numpy())
        return h.digest()

    def _one(self, pixels: torch.Tensor, thw: torch.Tensor, kwargs: dict[str, Any], key: bytes | None = None):
        key = key or self.pixel_key(pixels, thw)
        hit = self.store.get(key)
        if hit is not None:
            self.hits += 1
            return hit
        self.misses += 1
        with torch.no_grad():
            out = self.encode(pixels, grid_thw=thw[None], **kwargs)
        value = (out.pooler_output, list(out.deepstack_features or []))
        size = sum(t.numel() * t.element_size() for t in (value[0], *value[1]))
        if self.bytes + size <= self.max_bytes:
            self.store[key] = value
            self.bytes += size
        return value

    def __call__(self, hidden_states: torch.Tensor, grid_thw: torch.Tensor, **kwargs: Any) -> Any:
        from transformers.models.qwen3_vl.modeling_qwen3_vl import BaseModelOutputWithDeepstackFeatures

        kwargs["return_dict"] = True
        keys, self.given = self.given or [None] * len(grid_thw), None  # file keys serve one call only
        parts = [
            self._one(px, thw, kwargs, key)
            for px, thw, key in zip(torch.split(hidden_states, grid_thw.prod(-1).tolist()), grid_thw, keys, strict=True)
        ]
        deep = [torch.cat(level) for level in zip(*(p[1] for p in parts))]
        # last_hidden_state (the unmerged patches) is not kept: get_image_features reads only the merged tokens
        return BaseModelOutputWithDeepstackFeatures(
            last_hidden_state=None, pooler_output=torch.cat([p[0] for p in parts]), deepstack_features=deep
        )


def cache_frozen_tower(model: nn.Module, max_mb: float) -> TowerCache | None:
    """Install a TowerCache on `model`'s vision tower when it is frozen and `max_mb` > 0; else None."""
    from labrobfail_vlm.train.grounding import vision_module

    visual = vision_module(model)
    if max_mb <= 0 or any(p.requires_grad for p in visual.parameters()):
        return None
    return TowerCache(visual, max_mb)


def check_cache_mb(value: object, auto: bool = False) -> None:
    """A `tower_cache_mb` setting: a number of MB >= 0 (0: off), or "auto" where the caller resolves it (`auto`);
    else a one-line ConfigError (the training's, the bench's and the learning curve's alike)."""
    from labrobfail_vlm.config import ConfigError

    if auto and value == "auto":
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
        words = "auto or a number" if auto else "a number"
        raise ConfigError(f"tower_cache_mb: expected {words} of MB >= 0 (0: off), got {value!r}")


def inference_cache(model: nn.Module, max_mb: float, previous: TowerCache | None = None) -> TowerCache | None:
    """An inference model's tower behind a TowerCache (None when `max_mb` <= 0); the model's parameters stop
    requiring gradients. Passes over the same grids then encode each grid once (the bench's model, Q6-template and
    blind passes: the blind grey grid is one image). `previous`: another model's cache, whose outputs this one takes
    over when both towers hold the same weights, byte for byte (the learning curve's checkpoints of a frozen-tower
    run)."""
    from labrobfail_vlm.train.grounding import vision_module

    if max_mb <= 0:
        return None
    model.requires_grad_(False)
    cache = TowerCache(vision_module(model), max_mb)
    if previous is not None and previous.weights_digest() == cache.weights_digest():
        cache.store, cache.bytes = previous.store, previous.bytes
    return cache


def file_key(path: str) -> bytes:
    """A grid file's key in a TowerCache: its path, size and modification time (a rewritten file is a miss)."""
    st = os.stat(path)
    name = f"file:{os.path.abspath(path)}:{st.st_size}:{st.st_mtime_ns}"
    return hashlib.blake2b(name.encode(), digest_size=16).digest()
