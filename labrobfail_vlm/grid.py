"""The spatio-temporal keyframe grid: M keyframes x K camera views in one image.

This is the VLM's only visual input, at training and at inference, so it lives in
the model core. Layout (default `time_axis="columns"`, as in the paper's annotation
prompt): each column is a time step, each row a camera view. With more keyframes
than `columns`, time wraps into further bands of K rows, so cells stay square at
the default 1536x768 (8 columns x 2 bands x 2 views = 16 cells of 192x192, i.e.
6x6 visual tokens each for Qwen3-VL's 32 px per token). `time_axis="rows"` is the
transpose (the paper's method section).

The temporal index (1-based, the number a Q3 answer refers to) is drawn at the
top-left of every cell; `draw_index=False` omits it (the paper's ablation).
A prefix grid (`visible=n`) leaves cells after the n-th time step blank, for
online supervision of a running policy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Sequence

import cv2
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from labrobfail_vlm.config import ConfigError

BLANK = (24, 24, 24)  # grey, so the canvas is one memset


@dataclass(frozen=True)
class GridConfig:
    width: int = 1536
    height: int = 768
    max_frames: int = 16  # M: keyframes shown
    columns: int = 8  # time steps per band (per row band when time_axis="rows")
    time_axis: str = "columns"  # "columns" (paper's annotation prompt) or "rows" (paper's method section)
    draw_index: bool = True

    def __post_init__(self) -> None:
        if self.time_axis not in ("columns", "rows"):
            raise ValueError(f"grid.time_axis: expected 'columns' or 'rows', got {self.time_axis!r}")
        for name in ("width", "height", "max_frames", "columns"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"grid.{name}: must be a positive integer, got {getattr(self, name)!r}")

    @classmethod
    def from_dict(cls, d: dict) -> "GridConfig":
        """The config stored in a dataset's stats.json or a checkpoint's manifest (unknown keys ignored)."""
        return cls(**{k: v for k, v in d.items() if k in cls.__dataclass_fields__})

    @property
    def bands(self) -> int:
        return math.ceil(self.max_frames / self.columns)

    def shape(self, views: int) -> tuple[int, int]:
        """(rows, cols) of cells for `views` camera views."""
        if self.time_axis == "columns":
            return self.bands * views, self.columns
        return self.columns, self.bands * views

    def cell(self, t: int, k: int, views: int) -> tuple[int, int]:
        """Cell (row, col) of time step t (0-based) in view k."""
        band, i = divmod(t, self.columns)
        if self.time_axis == "columns":
            return band * views + k, i
        return i, band * views + k


def sample_keyframes(segments: Sequence[int], m: int) -> list[int]:
    """Pick at most m keyframe indices, favouring action transitions.

    `segments[i]` is the step (atomic action) keyframe i belongs to. The last keyframe of
    every step (the state an action leaves behind) and the first keyframe come first; the
    rest are filled evenly in time. Returned in temporal order.
    """
    n = len(segments)
    if n <= m:
        return list(range(n))
    ends = [i for i in range(n) if i == n - 1 or segments[i + 1] != segments[i]]
    starts = [i for i in range(n) if i == 0 or segments[i - 1] != segments[i]]
    chosen: list[int] = []
    for i in [0, *ends, *starts]:
        if i not in chosen and len(chosen) < m:
            chosen.append(i)
    rest = [i for i in range(n) if i not in chosen]
    need = m - len(chosen)
    if need > 0:
        picks = np.linspace(0, len(rest) - 1, need).round().astype(int)
        chosen.extend(rest[j] for j in dict.fromkeys(picks.tolist()))
    return sorted(chosen[:m])


def whole_grid_picks(names: Sequence[str | None], segments: Sequence[int], m: int) -> list[int]:
    """The keyframes a whole-trajectory grid of at most m frames shows: `sample_keyframes` over the trajectory's
    keyframes, where consecutive keyframes with one name count as one, shown by its last. A learned policy's control
    ticks are keyframes named after the plan keyframe they head for (the supervision loop's phase tracker), so its
    grid shows the plan's progress, not m of its 400 ticks; when that grouping leaves fewer than m, every keyframe
    counts (a one-cell grid of a policy the tracker could not place on the plan would show nothing). A scripted
    episode never has two keyframes in a row with one name, so for it this is `sample_keyframes(segments, m)`.
    One rule for the supervisor's final grid and the dataset's grids, so a policy's rollout written as a shard
    trains on the grid the supervisor is shown."""
    n = len(segments)
    units = [i for i in range(n) if i == n - 1 or names[i + 1] != names[i]]
    if len(units) < m:
        units = list(range(n))
    return [units[p] for p in sample_keyframes([segments[u] for u in units], m)]


def frame_for_keyframe(sampled: Sequence[int], keyframe: int) -> int:
    """1-based grid frame number where a failure at `keyframe` is first visible.

    Images are taken at the end of each keyframe, so the failure shows in the first sampled
    keyframe at or after it (the last one when it comes after every sampled keyframe).
    """
    for j, k in enumerate(sampled):
        if k >= keyframe:
            return j + 1
    return len(sampled)


@lru_cache(maxsize=256)
def _label(text: str, size: int) -> np.ndarray:
    """A rendered index tag (white digits on a dark box), cached: drawing text is the slow part."""
    font = ImageFont.load_default(size=size)
    left, top, right, bottom = font.getbbox(text)
    pad = max(2, size // 6)
    img = Image.new("RGB", (right - left + 2 * pad, bottom - top + 2 * pad), (0, 0, 0))
    ImageDraw.Draw(img).text((pad - left, pad - top), text, fill=(255, 255, 255), font=font)
    return np.asarray(img)


def index_tag(t: int, cell_height: int) -> np.ndarray:
    """The temporal index tag drawn at the top-left of time step t's cells (0-based t, shown as t + 1)."""
    return _label(str(t + 1), max(10, cell_height // 7))


def _fit_into(cell: np.ndarray, img: Image.Image | np.ndarray) -> None:
    """Resize keeping the aspect ratio, centred in `cell` (a view into the canvas, already blank).

    OpenCV's SIMD resize: Pillow's bilinear alone costs ~0.3 ms per cell, 10 ms for 32 cells.
    """
    a = np.asarray(img.convert("RGB") if isinstance(img, Image.Image) and img.mode != "RGB" else img, np.uint8)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"grid: frames must be HxWx3 RGB, got shape {a.shape}")
    h, w = cell.shape[:2]
    s = min(w / a.shape[1], h / a.shape[0])
    nw, nh = max(1, round(a.shape[1] * s)), max(1, round(a.shape[0] * s))
    if (nw, nh) != (a.shape[1], a.shape[0]):
        a = cv2.resize(a, (nw, nh), interpolation=cv2.INTER_LINEAR)
    y0, x0 = (h - nh) // 2, (w - nw) // 2
    cell[y0 : y0 + nh, x0 : x0 + nw] = a


def build_grid(
    frames: Sequence[Sequence[Image.Image | np.ndarray]], cfg: GridConfig = GridConfig(), visible: int | None = None
) -> Image.Image:
    """Compose `frames[view][t]` (already sampled, at most cfg.max_frames per view) into the grid.

    `visible`: show only the first `visible` time steps (a prefix grid); later cells stay blank.
    """
    if not frames or not frames[0]:
        raise ValueError("grid: no frames given")
    views, m = len(frames), len(frames[0])
    if any(len(v) != m for v in frames):
        raise ValueError(f"grid: views have unequal numbers of frames: {[len(v) for v in frames]}")
    if m > cfg.max_frames:
        raise ValueError(f"grid: {m} frames per view exceed grid.max_frames={cfg.max_frames}")
    rows, cols = cfg.shape(views)
    cw, ch = cfg.width // cols, cfg.height // rows
    canvas = np.full((cfg.height, cfg.width, 3), BLANK[0], np.uint8)
    shown = m if visible is None else max(0, min(int(visible), m))
    for k in range(views):
        for t in range(shown):
            r, c = cfg.cell(t, k, views)
            y, x = r * ch, c * cw
            _fit_into(canvas[y : y + ch, x : x + cw], frames[k][t])
            if cfg.draw_index:
                tag = index_tag(t, ch)
                th, tw = min(tag.shape[0], ch), min(tag.shape[1], cw)
                canvas[y : y + th, x : x + tw] = tag[:th, :tw]
    return Image.fromarray(canvas)


def fit_grid(img: Image.Image, cfg: GridConfig) -> Image.Image:
    """A grid image brought to the size the model was trained on. Only its shape can be read off the pixels: one of
    the same aspect ratio (within 1 %: the same rows and columns of cells, larger or smaller) is resized, since the
    model has seen cells of one size only and a 3x larger grid costs 9x the visual tokens; any other shape is
    another layout (more keyframes, other views) and is refused in one line rather than read wrongly."""
    w, h = img.size
    if (w, h) == (cfg.width, cfg.height):
        return img
    check_layout(w, h, cfg)
    return img.resize((cfg.width, cfg.height), Image.Resampling.BICUBIC)


def check_layout(w: int, h: int, cfg: GridConfig) -> None:
    """A one-line ConfigError unless a w x h grid has the aspect ratio of `cfg` (within 1 %)."""
    if abs(w * cfg.height - h * cfg.width) > 0.01 * h * cfg.width:
        raise ConfigError(
            f"grid: a {w}x{h} image is not the {cfg.width}x{cfg.height} layout the model was trained on "
            f"({cfg.max_frames} keyframes in {cfg.columns} columns, time along {cfg.time_axis}); send that grid, "
            "or the keyframes or videos per view and let it be composed"
        )
