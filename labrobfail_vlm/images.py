"""Safe image input for inference: every way a file can be wrong becomes a one-line ConfigError.

Checks: missing path, a directory where a file is expected, unreadable file, not an image,
corrupt or truncated data (fully decoded here, not lazily later), images too small to hold
a grid cell, and decompression bombs (pixel count checked from the header before decoding).
Files (`load_image`) and uploaded bytes (`decode_image`, the diagnosis server) go through the same checks.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import BinaryIO

from PIL import Image, UnidentifiedImageError

from labrobfail_vlm.config import ConfigError

MIN_SIDE = 32  # one visual token
MAX_PIXELS = 40_000_000  # well above a 4K grid; anything larger is refused before decoding
Image.MAX_IMAGE_PIXELS = MAX_PIXELS


class ImageTooLarge(ConfigError):
    """An image over the pixel limit (a decompression bomb): a server answers 413 rather than 400."""


def load_image(path: str | Path, field: str = "grid") -> Image.Image:
    p = Path(path)
    if not p.exists():
        raise ConfigError(f"{field}: {path} does not exist")
    if p.is_dir():
        raise ConfigError(f"{field}: {path} is a directory, expected an image file")
    try:  # a permission problem or an I/O error shows up here, before any decoding
        with open(p, "rb") as f:
            f.read(16)
    except OSError as e:
        raise ConfigError(f"{field}: {path} is not readable ({e.strerror or type(e).__name__})") from None
    return open_image(p, str(path), field)


def decode_image(data: bytes, name: str, field: str) -> Image.Image:
    """An uploaded image (bytes), with the same checks as a file; `name` stands for it in messages."""
    import io

    return open_image(io.BytesIO(data), name, field)


def open_image(src: str | Path | BinaryIO, name: str, field: str) -> Image.Image:
    """Decode fully (not lazily later) into RGB; every failure is a one-line ConfigError naming `field`/`name`."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(src) as im:
                w, h = im.size
                if w * h > MAX_PIXELS:
                    raise ImageTooLarge(f"{field}: {name} is {w}x{h}, over the {MAX_PIXELS:,} pixel limit")
                im.load()
                img = im.convert("RGB")
    except ConfigError:
        raise
    except (Image.DecompressionBombError, Image.DecompressionBombWarning):
        raise ImageTooLarge(f"{field}: {name} is too large (decompression bomb guard)") from None
    except UnidentifiedImageError:
        raise ConfigError(f"{field}: {name} is not an image file") from None
    except (OSError, SyntaxError, ValueError) as e:
        raise ConfigError(f"{field}: {name} is corrupt or truncated ({str(e).splitlines()[0][:120]})") from None
    if min(img.size) < MIN_SIDE:
        raise ConfigError(f"{field}: {name} is {img.width}x{img.height}; at least {MIN_SIDE} px per side needed")
    return img


def load_frames(folder: str | Path) -> tuple[list[str], list[list[Image.Image]]]:
    """`frames=DIR`: one sub-folder per camera view, each with the same number of keyframe images."""
    root = Path(folder)
    if not root.is_dir():
        raise ConfigError(f"frames: {folder} is not a directory")
    views = sorted(d for d in root.iterdir() if d.is_dir())
    if not views:
        raise ConfigError(f"frames: {folder} has no view sub-folders (expected DIR/<view>/<frame>.png)")
    exts = {".png", ".jpg", ".jpeg", ".bmp", ".webp"}
    files = [sorted(f for f in v.iterdir() if f.suffix.lower() in exts) for v in views]
    counts = {v.name: len(f) for v, f in zip(views, files)}
    if len(set(counts.values())) != 1:
        raise ConfigError(f"frames: views have unequal numbers of frames: {counts}")
    if not next(iter(counts.values())):
        raise ConfigError(f"frames: no images in {folder}")
    return [v.name for v in views], [[load_image(f, "frames") for f in fs] for fs in files]
