"""Image augmentation of keyframe views, drawn once and applied alike to every frame of a view.

A shift and a zoom per view stand for a camera that stood a little elsewhere; a colour change per grid for other
light and white balance. The same `Augment` applied to both twins of a success/failure pair keeps their only
difference the failure (the twins share one initial state and render pixel-identically until it). Points (pixel
positions of things in a view) go through the same shift and zoom, so position targets follow the picture.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import cv2
import numpy as np
from PIL import Image

from labrobfail_vlm.grid import BLANK, GridConfig, index_tag


@dataclass(frozen=True)
class AugmentConfig:
    colour: float = 0.25  # brightness, contrast, saturation factors in [1 - c, 1 + c]
    shift_px: float = 8.0  # per view, in pixels of the view image
    scale: float = 0.1  # per view, zoom in [1 - s, 1 + s] about the image centre
    hue: float | None = None  # hue shift up to this many turns (0.5: any hue); None: colour / 5 turn
    # False: no pixel ends more saturated than it was rendered (hue, brightness and contrast change, saturation only
    # falls), so augmentation adds no saturation the family's pictures lack: the sealed scene family is told apart by
    # saturation (sim_backends/pybullet/scene.py), and a contrast or saturation gain reaches it from any family.
    raise_saturation: bool = True

    def __post_init__(self) -> None:
        if not (0 <= self.colour < 1 and self.shift_px >= 0 and 0 <= self.scale < 0.5):
            raise ValueError(f"augment: expected 0 <= colour < 1, shift_px >= 0, 0 <= scale < 0.5, got {self}")
        if self.hue is not None and not 0 <= self.hue <= 0.5:
            raise ValueError(f"augment: expected 0 <= hue <= 0.5 (turns), got {self.hue!r}")
        if not isinstance(self.raise_saturation, bool):
            raise ValueError(f"augment: expected raise_saturation true or false, got {self.raise_saturation!r}")

    @classmethod
    def from_section(cls, section: Mapping[str, Any]) -> "AugmentConfig":
        """From a config's `augment` section (train.yaml's also holds `enabled`, which is not a setting of the draw);
        YAML numbers arrive as int or float alike."""
        values: dict[str, Any] = {}
        for key in ("colour", "shift_px", "scale", "hue"):
            v = section.get(key)
            if v is None and key == "hue":
                values[key] = None
            elif isinstance(v, (int, float)) and not isinstance(v, bool):
                values[key] = float(v)
            else:
                raise ValueError(f"augment.{key}: expected a number, got {v!r}")
        raise_sat = section.get("raise_saturation", True)  # absent (an older config or tower card): it did raise
        if not isinstance(raise_sat, bool):
            raise ValueError(f"augment.raise_saturation: expected true or false, got {raise_sat!r}")
        return cls(**values, raise_saturation=raise_sat)

    @property
    def hue_turns(self) -> float:
        return self.colour / 5 if self.hue is None else self.hue


@dataclass(frozen=True)
class Augment:
    """One draw: an affine per view (zoom, dx, dy) and one colour change (brightness, contrast, saturation, hue)."""

    views: tuple[tuple[float, float, float], ...]
    colour: tuple[float, float, float, float]
    raise_saturation: bool = True  # AugmentConfig.raise_saturation

    @classmethod
    def draw(cls, cfg: AugmentConfig, views: int, rng: np.random.Generator) -> "Augment":
        v = tuple(
            (
                float(rng.uniform(1 - cfg.scale, 1 + cfg.scale)),
                float(rng.uniform(-cfg.shift_px, cfg.shift_px)),
                float(rng.uniform(-cfg.shift_px, cfg.shift_px)),
            )
            for _ in range(views)
        )
        c = cfg.colour
        col = (
            float(rng.uniform(1 - c, 1 + c)),
            float(rng.uniform(1 - c, 1 + c)),
            float(rng.uniform(1 - c, 1 + c)),
            float(rng.uniform(-cfg.hue_turns, cfg.hue_turns)),
        )
        return cls(v, col, cfg.raise_saturation)

    def matrix(self, view: int, size: tuple[int, int]) -> np.ndarray:
        """2x3 affine of view `view` for an image of (width, height)."""
        s, dx, dy = self.views[view]
        cx, cy = size[0] / 2, size[1] / 2
        return np.array([[s, 0, cx - s * cx + dx], [0, s, cy - s * cy + dy]], np.float64)

    def image(self, img: np.ndarray, view: int) -> np.ndarray:
        """An HxWx3 uint8 view image, shifted, zoomed and recoloured."""
        h, w = img.shape[:2]
        out = cv2.warpAffine(
            img, self.matrix(view, (w, h)), (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        bright, contrast, sat, hue = self.colour
        before = out
        x = out.astype(np.float32)
        mean = x.mean()
        x = (x - mean) * contrast + mean * bright
        grey = x.mean(axis=2, keepdims=True)
        x = grey + (x - grey) * sat
        out = np.clip(x, 0, 255).astype(np.uint8)
        if hue:
            hsv = cv2.cvtColor(out, cv2.COLOR_RGB2HSV)
            hsv[..., 0] = ((hsv[..., 0].astype(np.int32) + int(round(hue * 180))) % 180).astype(np.uint8)
            out = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
        return out if self.raise_saturation else cap_saturation(out, before)

    def points(self, pts: np.ndarray, view: int, size: tuple[int, int]) -> np.ndarray:
        """(..., 2) pixel positions in view `view` -> where the augmented picture shows them (NaN stays NaN)."""
        m = self.matrix(view, size)
        return pts @ m[:, :2].T + m[:, 2]


def hsv_saturation(img: np.ndarray) -> np.ndarray:
    """Per-pixel HSV saturation (max - min) / max of an ...x3 image, 0 where the pixel is black."""
    x = img.astype(np.float32)
    hi, lo = x.max(axis=-1), x.min(axis=-1)
    return np.where(hi > 0, (hi - lo) / np.maximum(hi, 1e-6), 0.0)


def cap_saturation(img: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """`img` with each pixel's saturation brought down to at most `ref`'s at that pixel, keeping its hue and value
    (HSV): the channels move toward the pixel's maximum. Rounded up, so the result is never above `ref`'s."""
    s_img, s_ref = hsv_saturation(img), hsv_saturation(ref)
    over = s_img > s_ref
    if not over.any():
        return img
    x = img.astype(np.float32)
    hi = x.max(axis=-1, keepdims=True)
    k = np.where(over, s_ref / np.maximum(s_img, 1e-6), 1.0)[..., None]
    return np.clip(np.ceil(hi - (hi - x) * k), 0, 255).astype(np.uint8)


def augment_views(frames: Sequence[Sequence[np.ndarray]], aug: Augment | None) -> list[list[np.ndarray]]:
    """frames[view][t] -> the same, augmented (each view with its own affine; one colour change for all)."""
    if aug is None:
        return [list(v) for v in frames]
    return [[aug.image(np.asarray(f), k) for f in view] for k, view in enumerate(frames)]


def augment_grid(img: Image.Image, grid: GridConfig, views: int, aug: Augment) -> Image.Image:
    """A composed keyframe grid, augmented as if its views had been augmented before composing: each shown cell
    gets its view's shift and zoom and the colour change; the index tag is lifted off first (its box filled from
    the row under it) and drawn again on top, so it stays where and as the grid builder put it."""
    canvas = np.array(img.convert("RGB"))
    rows, cols = grid.shape(views)
    cw, ch = grid.width // cols, grid.height // rows
    for k in range(views):
        for t in range(grid.max_frames):
            r, c = grid.cell(t, k, views)
            cell = canvas[r * ch : (r + 1) * ch, c * cw : (c + 1) * cw]
            if (cell == BLANK[0]).all():  # a cell the grid leaves blank (no such frame, or past a prefix cut)
                continue
            tag = index_tag(t, ch) if grid.draw_index else None
            th, tw = (min(tag.shape[0], ch - 1), min(tag.shape[1], cw)) if tag is not None else (0, 0)
            if tag is not None:
                cell[:th, :tw] = cell[th : th + 1, :tw]
            cell[:] = aug.image(cell, k)
            if tag is not None:
                cell[:th, :tw] = tag[:th, :tw]
    return Image.fromarray(canvas)
