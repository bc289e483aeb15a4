"""Video in: a recorded trajectory (one video per camera view) -> the keyframes of the grid the model was trained on.

A robot stack records video, not keyframe grids. Each video is read twice with OpenCV (its FFmpeg backend): a first
pass checks every frame decodes and measures motion on 32 x 32 grey thumbnails (nothing larger is kept), a second
keeps only the picked frames, so memory is the picked frames whatever the video's length. Two ways to pick:

- `uniform` (the default): evenly spaced in time, the first and the last frame included. The simulator's grids
  show keyframes at the ends of the plan's steps, which fall unevenly in time; uniform is the choice that needs no
  idea of the steps and is what a reader of the grid expects ("frame 4 of 8 is halfway").
- `motion`: evenly spaced in accumulated motion (the mean absolute change between consecutive thumbnails), so
  stretches where the arm moves get more keyframes and idle waits fewer; a still video falls back to uniform.

Views are recordings of one trajectory: frames are picked on the first view's timeline (motion summed over the
views) and every other view takes the frames at the same fraction of its length. Every problem (a missing file, not
a video, a truncated one, frames too large) is a one-line ConfigError naming the field.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from PIL import Image

from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.images import MAX_PIXELS, MIN_SIDE, ImageTooLarge

KEYFRAME_MODES = ("uniform", "motion")
MAX_VIDEO_FRAMES = 100_000  # about an hour at 30 fps; longer recordings are cut to the trajectory first
THUMB = 32  # motion is measured on THUMB x THUMB grey thumbnails


def _capture(path: Path, name: str, field: str):  # -> cv2.VideoCapture
    # FFmpeg's own log lines ("moov atom not found") would print around our one-line error: quiet before first use
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    # local files only: a playlist (HLS, concat) inside an upload must not make FFmpeg open URLs or other files
    os.environ.setdefault("OPENCV_FFMPEG_CAPTURE_OPTIONS", "protocol_whitelist;file")
    import cv2

    log = cv2.utils.logging
    if log.getLogLevel() > log.LOG_LEVEL_ERROR:  # ... and OpenCV's warnings ("can't be used to capture by name")
        log.setLogLevel(log.LOG_LEVEL_ERROR)
    if not path.exists():
        raise ConfigError(f"{field}: {name} does not exist")
    if path.is_dir():
        raise ConfigError(f"{field}: {name} is a directory, expected a video file")
    try:
        with open(path, "rb") as f:
            f.read(16)
    except OSError as e:
        raise ConfigError(f"{field}: {name} is not readable ({e.strerror or type(e).__name__})") from None
    still = _image_format(path)  # FFmpeg reads a still as a one-frame "video" whose stated frame count is garbage
    if still:
        raise ConfigError(f"{field}: {name} is a {still} image, not a video (a grid or frames go elsewhere)")
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    if not cap.isOpened():
        raise ConfigError(f"{field}: {name} is not a video OpenCV can read (or its header is truncated)")
    return cap


STILL_FORMATS = ("PNG", "JPEG", "BMP", "TIFF", "WEBP")  # not GIF or MPEG: Pillow reads those, and so does FFmpeg


def _image_format(path: Path) -> str | None:
    """The still-image format Pillow finds in the file's header (one frame of PNG, JPEG, ...), or None."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            still = im.format in STILL_FORMATS and getattr(im, "n_frames", 1) == 1
            return im.format if still else None
    except Exception:  # noqa: BLE001 - anything Pillow cannot open (or refuses: a decompression bomb) is FFmpeg's
        return None


@dataclass(frozen=True)
class VideoInfo:
    """One video after the first pass: its size, frame count and per-frame motion (frame 0: 0)."""

    path: Path
    name: str
    field: str
    width: int
    height: int
    fps: float
    motion: np.ndarray

    @property
    def frames(self) -> int:
        return len(self.motion)


def header(path: str | Path, field: str = "video", name: str | None = None) -> tuple[int, int, int]:
    """(width, height, frame count as the container states it) without decoding a frame: for pricing memory."""
    cap, w, h, n = _opened(Path(path), name or str(path), field)
    cap.release()
    return w, h, n


def _opened(p: Path, name: str, field: str):  # -> (cv2.VideoCapture, width, height, stated frame count)
    """A capture and what its header states, the frame size checked (the caller releases the capture)."""
    import cv2

    cap = _capture(p, name, field)
    w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    try:
        _check_size(w, h, name, field)
    except ConfigError:
        cap.release()
        raise
    return cap, w, h, int(cap.get(cv2.CAP_PROP_FRAME_COUNT))


def _check_size(w: int, h: int, name: str, field: str) -> None:
    if w * h > MAX_PIXELS:
        raise ImageTooLarge(f"{field}: {name} has {w}x{h} frames, over the {MAX_PIXELS:,} pixel limit")
    if min(w, h) < MIN_SIDE:
        raise ConfigError(f"{field}: {name} has {w}x{h} frames; at least {MIN_SIDE} px per side needed")


def scan(
    path: str | Path, field: str = "video", name: str | None = None, max_frames: int = MAX_VIDEO_FRAMES
) -> VideoInfo:
    """The first pass: every frame decoded once (a truncated video is refused, and one with more than `max_frames`
    or whose frames change size from what its header priced), motion measured on thumbnails."""
    import cv2

    p, name = Path(path), name or str(path)
    cap, w, h, stated = _opened(p, name, field)  # one capture: the header's size, then every frame
    motion: list[float] = []
    prev: np.ndarray | None = None
    try:
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            if len(motion) == max_frames:
                raise ConfigError(f"{field}: {name} has more than {max_frames:,} frames; cut it to the trajectory")
            if frame.shape[:2] != (h, w):  # memory was priced from the header's size
                raise ConfigError(
                    f"{field}: {name} changes frame size ({w}x{h}, then {frame.shape[1]}x{frame.shape[0]})"
                )
            thumb = cv2.resize(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY), (THUMB, THUMB), interpolation=cv2.INTER_AREA)
            thumb = thumb.astype(np.float32)
            motion.append(0.0 if prev is None else float(np.abs(thumb - prev).mean()))
            prev = thumb
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    finally:
        cap.release()
    if not motion:
        raise ConfigError(f"{field}: {name} has no frame that decodes")
    if stated > 0 and len(motion) < stated:
        raise ConfigError(f"{field}: {name} is truncated or corrupt: {len(motion)} of its {stated} frames decode")
    return VideoInfo(p, name, field, w, h, fps, np.asarray(motion, np.float64))


def pick(motion: np.ndarray, m: int, mode: str = "uniform") -> list[int]:
    """m frame indices in temporal order (all of them when the video has no more than m), first and last included."""
    if mode not in KEYFRAME_MODES:
        raise ConfigError(f"keyframes: expected one of {', '.join(KEYFRAME_MODES)}, got {mode!r}")
    n = len(motion)
    if n <= m:
        return list(range(n))
    if m == 1:
        return [n - 1]  # the state the trajectory ends in
    cum = np.cumsum(motion)
    if mode == "uniform" or cum[-1] <= 0:
        return np.linspace(0, n - 1, m).round().astype(int).tolist()  # distinct: the step is at least 1
    idx = np.searchsorted(cum, np.linspace(0, cum[-1], m), side="left").clip(0, n - 1)
    idx[0], idx[-1] = 0, n - 1
    for j in range(1, m):  # distinct and increasing: a burst of motion in one frame does not take two keyframes
        idx[j] = max(idx[j], idx[j - 1] + 1)
    # ... and still ending at the last frame (the minimum of two increasing sequences increases)
    return np.minimum(idx, n - m + np.arange(m)).tolist()


def grab(info: VideoInfo, indices: Sequence[int]) -> list[Image.Image]:
    """The second pass: the frames at `indices` (sorted), as RGB images."""
    import cv2

    want, out = set(indices), {}
    cap = _capture(info.path, info.name, info.field)
    try:
        for i in range(max(indices) + 1):
            if not cap.grab():
                raise ConfigError(f"{info.field}: {info.name} changed while it was read (frame {i} is gone)")
            if i in want:
                ok, frame = cap.retrieve()
                if not ok:
                    raise ConfigError(f"{info.field}: {info.name}: frame {i} does not decode")
                out[i] = Image.fromarray(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
    finally:
        cap.release()
    return [out[i] for i in indices]


def keyframes(videos: Sequence[VideoInfo], m: int, mode: str = "uniform") -> list[list[Image.Image]]:
    """Per view, the m keyframes (fewer if the first view is shorter), picked on the first view's timeline."""
    if not videos:
        raise ConfigError("video: give one video per camera view")
    n0 = videos[0].frames
    t0 = np.arange(n0) / max(n0 - 1, 1)
    total = sum(np.interp(t0, np.arange(v.frames) / max(v.frames - 1, 1), v.motion) for v in videos)
    picked = pick(np.asarray(total), m, mode)
    frac = [i / max(n0 - 1, 1) for i in picked]
    return [grab(v, [int(round(f * (v.frames - 1))) for f in frac]) for v in videos]


def read_keyframes(
    paths: Sequence[str | Path], m: int, mode: str = "uniform", field: str = "video"
) -> list[list[Image.Image]]:
    """`scan` every view's video, then `keyframes`."""
    return keyframes([scan(p, field) for p in paths], m, mode)
