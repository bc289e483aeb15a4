"""Validate a `POST /diagnose` form and turn it into a DiagnosisRequest, or fail with one line.

Fields (multipart/form-data):
    grid            one keyframe-grid image (PNG/JPEG/...), as built by labrobfail_vlm.grid
    frames.<view>   or per-view keyframe images, repeated in temporal order (e.g. frames.front, frames.side);
                    the server composes the grid in the layout the model was trained on
    task            the task in words (optional)
    prefix          k: a partial trajectory, only its first k keyframes shown (optional); Q3 answers 1..k
    objects         comma-separated object/place names of the scene (Q6 template mode; optional)
Every problem is a ConfigError naming the field (400), or ImageTooLarge for a decompression bomb (413).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Sequence

from labrobfail_vlm.analyzer import DiagnosisRequest, frames_to_grid
from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.grid import GridConfig
from labrobfail_vlm.images import decode_image

FIELDS = "grid or frames.<view> files, task, prefix, objects"
TEXT_FIELDS = ("task", "prefix", "objects")
MAX_TEXT = 2000  # characters of a text field
MAX_VIEWS = 8
_VIEW = re.compile(r"^frames\.([A-Za-z0-9_-]{1,32})$")


@dataclass(frozen=True)
class Upload:
    """One uploaded file, read into memory (the whole body is bounded by the server's upload limit)."""

    filename: str
    data: bytes


def parse(items: Sequence[tuple[str, str | Upload]], grid: GridConfig) -> DiagnosisRequest:
    text: dict[str, str] = {}
    image: Upload | None = None
    views: dict[str, list[Upload]] = {}
    for name, value in items:
        view = _VIEW.match(name)
        if name == "grid" or view:
            if not isinstance(value, Upload):
                raise ConfigError(f"{name}: expected an uploaded image file, got a text value")
            if name == "grid":
                if image is not None:
                    raise ConfigError("grid: given more than once (send one grid image)")
                image = value
            elif view is not None:
                if view.group(1) not in views and len(views) == MAX_VIEWS:
                    raise ConfigError(f"{name}: at most {MAX_VIEWS} camera views")
                views.setdefault(view.group(1), []).append(value)
        elif name in TEXT_FIELDS:
            if not isinstance(value, str):
                raise ConfigError(f"{name}: expected a text value, got a file")
            if name in text:
                raise ConfigError(f"{name}: given more than once")
            if len(value) > MAX_TEXT:
                raise ConfigError(f"{name}: longer than {MAX_TEXT} characters")
            text[name] = value.strip()
        else:
            raise ConfigError(f"unknown field {name[:64]!r}; expected {FIELDS}")
    if image is None and not views:
        raise ConfigError(f"missing image: send a grid file or frames.<view> files ({FIELDS})")
    if image is not None and views:
        raise ConfigError("grid and frames.<view> given together: send one or the other")
    objects = [o.strip() for o in text.get("objects", "").split(",") if o.strip()]
    if image is not None:
        img = decode_image(image.data, _name(image), "grid")
        k = _prefix(text.get("prefix"), grid.max_frames)
        return DiagnosisRequest(img, text.get("task", ""), k, objects)
    counts = {v: len(f) for v, f in views.items()}
    if len(set(counts.values())) != 1:
        raise ConfigError(f"frames: views have unequal numbers of frames: {counts}")
    frames = [[decode_image(u.data, _name(u), f"frames.{v}") for u in fs] for v, fs in views.items()]
    shown = min(len(frames[0]), grid.max_frames)  # more keyframes than the grid holds are thinned evenly
    k = _prefix(text.get("prefix"), shown)
    return DiagnosisRequest(frames_to_grid(frames, grid, visible=k), text.get("task", ""), k or shown, objects)


def _name(u: Upload) -> str:
    return repr(u.filename[:64]) if u.filename else "the upload"


def _prefix(value: str | None, hi: int) -> int | None:
    if value is None or value == "":
        return None
    if not value.isdigit() or not 1 <= int(value) <= hi:
        raise ConfigError(f"prefix: expected an integer from 1 to {hi} (keyframes shown), got {value[:32]!r}")
    return int(value)
