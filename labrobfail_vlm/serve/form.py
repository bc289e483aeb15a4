"""Validate a `POST /diagnose` form and turn it into a DiagnosisRequest, or fail with one line.

Fields (multipart/form-data):
    grid            one keyframe-grid image (PNG/JPEG/...), as built by labrobfail_vlm.grid
    frames.<view>   or per-view keyframe images, repeated in temporal order (e.g. frames.front, frames.side);
                    the server composes the grid in the layout the model was trained on
    video.<view>    or one video per view (e.g. video.front, video.side, in the grid's view order): the server
                    picks the keyframes (labrobfail_vlm/video.py) and composes the grid
    keyframes       how video keyframes are picked: uniform (in time, the default) or motion (optional)
    task            the task in words (optional)
    prefix          k: a partial trajectory, only its first k keyframes shown (optional); Q3 answers 1..k
    objects         comma-separated object/place names of the scene (Q6 template mode; optional)
Every problem is a ConfigError naming the field (400), or ImageTooLarge (413) for an image over the pixel limit
or a request whose images would take more than `max_bytes` decoded.

Two steps, so the server can reserve memory in between: `plan` checks the fields and reads only the image headers
(the decoded size is known before a pixel is decoded); `build` decodes and composes the grid. `parse` does both.
"""

from __future__ import annotations

import io
import os
import re
import tempfile
import warnings
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from typing import Iterator, Sequence

from PIL import Image, UnidentifiedImageError

from labrobfail_vlm.analyzer import DiagnosisRequest, frames_to_grid
from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.grid import GridConfig, check_layout, fit_grid
from labrobfail_vlm.images import ImageTooLarge, decode_image
from labrobfail_vlm.serve.budget import mb

FIELDS = "grid, frames.<view> or video.<view> files, task, prefix, objects, keyframes"
TEXT_FIELDS = ("task", "prefix", "objects", "keyframes")
MAX_TEXT = 2000  # characters of a text field
MAX_VIEWS = 8
MAX_REQUEST_DECODE_BYTES = 256 << 20  # the default per-request limit (ServeConfig.max_request_decode_bytes)
MAX_VIDEO_FRAMES = 9000  # frames one uploaded video may hold (5 min at 30 fps): each is decoded twice
RGB_BYTES = 4  # PIL keeps an RGB image at 4 bytes per pixel (padded)
# bytes per grid pixel a request holds once decoded, until its reply: the RGB grid in the queue (4), the model
# thread's RGB copy of it (FailureAnalyzer._prepare, 4) and the image processor's float32 RGB arrays (12; measured:
# ~10 per pixel for a 15 MP grid)
KEPT_BYTES = 4 + 4 + 12
_VIEW = re.compile(r"^frames\.([A-Za-z0-9_-]{1,32})$")
_VIDEO = re.compile(r"^video\.([A-Za-z0-9_-]{1,32})$")
_PREFIX = re.compile(r"[0-9]{1,6}")  # ASCII digits only: str.isdigit() also accepts "²", which int() refuses
_CONTROL = re.compile(r"[\x00-\x08\x0b\x0c\x0e-\x1f\x7f]")  # control characters other than tab and newlines


@dataclass(frozen=True)
class Upload:
    """One uploaded file, read into memory (the whole body is bounded by the server's upload limit)."""

    filename: str
    data: bytes


@dataclass
class Plan:
    """A checked form whose images are not decoded yet. `cost`: the most memory its images will take (bytes),
    reserved before decoding; `kept`: what it still holds once decoded, until its reply (KEPT_BYTES a pixel)."""

    text: dict[str, str]
    image: Upload | None
    views: dict[str, list[Upload]]
    prefix: int | None
    cost: int
    kept: int
    videos: dict[str, Upload] | None = None
    fit: bool = False  # a grid of another size is brought to the model's (grid.fit_grid) before it is queued


@dataclass(frozen=True)
class Header:
    """What an image's header says: size, channels, bytes per sample, and the bytes decoding it to RGB takes."""

    width: int
    height: int
    bands: int
    sample: int

    @property
    def decode(self) -> int:
        """PIL holds max(4, channels x bytes per sample) a pixel while decoding (any multi-band image takes 4; a
        16-bit file is counted at its full depth, 8 for 16-bit RGBA, so the estimate is never below what the
        decoder allocates), and the RGB copy 4 more."""
        return self.width * self.height * (max(4, self.bands * self.sample) + RGB_BYTES)

    def describe(self) -> str:
        return f"{self.width}x{self.height} px with {self.bands} channel(s) of {8 * self.sample} bits"


def read_header(u: Upload, fld: str) -> Header:
    """The header of an uploaded image, without decoding a pixel; a bomb is ImageTooLarge, garbage a ConfigError."""
    name = _name(u)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(u.data)) as im:  # lazy: reads the header, decodes nothing
                (w, h), bands = im.size, len(im.getbands())
                raw = " ".join(str(t[3]) for t in im.tile[:1]) + " " + im.mode
    except (Image.DecompressionBombError, Image.DecompressionBombWarning):
        raise ImageTooLarge(f"{fld}: {name} is too large (decompression bomb guard)") from None
    except UnidentifiedImageError:
        raise ConfigError(f"{fld}: {name} is not an image file") from None
    except Exception as e:  # noqa: BLE001 - PIL's plugins raise many types on hostile headers; all mean "corrupt"
        raise ConfigError(f"{fld}: {name} is corrupt ({type(e).__name__})") from None
    return Header(w, h, bands, 2 if ";16" in raw else 1)


def plan(
    items: Sequence[tuple[str, str | Upload]],
    grid: GridConfig,
    max_bytes: int = MAX_REQUEST_DECODE_BYTES,
    fit: bool = False,
) -> Plan:
    """Check every field and price the images from their headers; ImageTooLarge if they exceed `max_bytes`. `fit`:
    the model names its grid, so a grid image of another aspect ratio is refused here and one of another size
    resized in `build` (grid.fit_grid)."""
    text: dict[str, str] = {}
    image: Upload | None = None
    views: dict[str, list[Upload]] = {}
    videos: dict[str, Upload] = {}
    for name, value in items:
        view = _VIEW.match(name)
        if (video := _VIDEO.match(name)) is not None:
            if not isinstance(value, Upload):
                raise ConfigError(f"{name}: expected an uploaded video file, got a text value")
            if video.group(1) in videos:
                raise ConfigError(f"{name}: given more than once (one video per camera view)")
            if len(videos) == MAX_VIEWS:
                raise ConfigError(f"{name}: at most {MAX_VIEWS} camera views")
            videos[video.group(1)] = value
        elif name == "grid" or view:
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
            text[name] = _text(name, value, text)
        else:
            raise ConfigError(f"unknown field {name[:64]!r}; expected {FIELDS}")
    if sum(map(bool, (image is not None, views, videos))) != 1:
        what = "missing image: send" if image is None and not views and not videos else "send exactly"
        raise ConfigError(f"{what} one of a grid file, frames.<view> files or video.<view> files ({FIELDS})")
    if text.get("keyframes", "uniform") not in ("uniform", "motion"):
        raise ConfigError(f"keyframes: expected uniform or motion, got {text['keyframes'][:32]!r}")
    if videos:
        return _plan_videos(text, videos, grid, max_bytes)
    if image is not None:
        hd = read_header(image, "grid")
        if fit:
            check_layout(hd.width, hd.height, grid)
        kept = hd.width * hd.height * KEPT_BYTES
        cost = max(hd.decode, kept)
        if cost > max_bytes:
            raise ImageTooLarge(
                f"grid: {_name(image)} is too large to decode: {hd.describe()} takes ~{mb(cost)} "
                f"to decode and diagnose, over the {mb(max_bytes)} per-request limit"
            )
        return Plan(text, image, {}, _prefix(text.get("prefix"), grid.max_frames), cost, kept, fit=fit)
    counts = {v: len(f) for v, f in views.items()}
    if len(set(counts.values())) != 1:
        raise ConfigError(f"frames: views have unequal numbers of frames: {counts}")
    shown = min(next(iter(counts.values())), grid.max_frames)  # more keyframes than the grid holds are thinned
    k = _prefix(text.get("prefix"), shown)
    # every frame stays decoded until the grid (canvas + image) is composed; then the grid is held as any grid
    px = grid.width * grid.height
    kept, frames = px * KEPT_BYTES, 2 * px * RGB_BYTES
    for v, fs in views.items():
        for u in fs:
            frames += read_header(u, f"frames.{v}").decode
            if max(frames, kept) > max_bytes:
                raise ImageTooLarge(
                    f"frames: the keyframes and the grid composed from them are too large to decode: "
                    f"over the {mb(max_bytes)} per-request limit (send fewer or smaller frames)"
                )
    cost = max(frames, kept)
    return Plan(text, None, views, k, cost, kept)


def _plan_videos(text: dict[str, str], videos: dict[str, Upload], grid: GridConfig, max_bytes: int) -> Plan:
    """Videos priced from their headers: the keyframes kept per view, a frame being decoded, the grid composed."""
    from labrobfail_vlm.video import header

    px = grid.width * grid.height
    kept, cost, shown = px * KEPT_BYTES, 2 * px * RGB_BYTES, grid.max_frames
    for v, u in videos.items():
        with _spooled(u) as path:
            w, h, n = header(path, f"video.{v}", _name(u))
        if not 0 < n <= MAX_VIDEO_FRAMES:  # decoding is bounded by what the container states, checked in `scan`
            raise ImageTooLarge(
                f"video.{v}: {_name(u)} states {n} frames; 1 to {MAX_VIDEO_FRAMES} are accepted (cut the video "
                "to the trajectory)"
            )
        shown = min(shown, n)
        cost += (grid.max_frames + 2) * w * h * RGB_BYTES
        if max(cost, kept) > max_bytes:
            raise ImageTooLarge(
                f"video.{v}: the keyframes of {_name(u)} ({w}x{h} px) and the grid take ~{mb(cost)} decoded, over "
                f"the {mb(max_bytes)} per-request limit (send smaller videos)"
            )
    return Plan(text, None, {}, _prefix(text.get("prefix"), shown), max(cost, kept), kept, videos)


@contextmanager
def _spooled(u: Upload) -> Iterator[str]:
    """An uploaded video as a temporary file (OpenCV reads files, not memory), removed afterwards."""
    # a fixed name: FFmpeg finds the container from the bytes, and a client's file name never picks its demuxer
    fd, path = tempfile.mkstemp(prefix="labrobfail-video-", suffix=".bin")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(u.data)
        yield path
    finally:
        os.unlink(path)


def _video_frames(p: Plan, grid: GridConfig) -> list[list[Image.Image]]:
    from labrobfail_vlm.video import keyframes, scan

    assert p.videos is not None
    with ExitStack() as stack:
        clips = [
            scan(stack.enter_context(_spooled(u)), f"video.{v}", _name(u), MAX_VIDEO_FRAMES)
            for v, u in p.videos.items()
        ]
        return keyframes(clips, grid.max_frames, p.text.get("keyframes") or "uniform")


def build(p: Plan, grid: GridConfig) -> DiagnosisRequest:
    """Decode the planned images (fully, with images.py's checks) and compose the request."""
    objects = [o.strip() for o in p.text.get("objects", "").split(",") if o.strip()]
    task = p.text.get("task", "")
    if p.videos:
        frames = _video_frames(p, grid)
        shown = min(len(frames[0]), grid.max_frames)
        if p.prefix is not None and p.prefix > shown:
            raise ConfigError(f"prefix: expected an integer from 1 to {shown} (keyframes shown), got {p.prefix}")
        return DiagnosisRequest(frames_to_grid(frames, grid, visible=p.prefix), task, p.prefix or shown, objects)
    if p.image is not None:
        img = _decode(p.image, "grid")
        return DiagnosisRequest(fit_grid(img, grid) if p.fit else img, task, p.prefix, objects)
    frames = [[_decode(u, f"frames.{v}") for u in fs] for v, fs in p.views.items()]
    shown = min(len(frames[0]), grid.max_frames)
    return DiagnosisRequest(frames_to_grid(frames, grid, visible=p.prefix), task, p.prefix or shown, objects)


def parse(
    items: Sequence[tuple[str, str | Upload]],
    grid: GridConfig,
    max_bytes: int = MAX_REQUEST_DECODE_BYTES,
    fit: bool = False,
) -> DiagnosisRequest:
    return build(plan(items, grid, max_bytes, fit), grid)


def _decode(u: Upload, fld: str):
    try:
        return decode_image(u.data, _name(u), fld)
    except ConfigError:
        raise
    except Exception as e:  # noqa: BLE001 - a PIL plugin failing on hostile data is the upload's fault, not ours
        raise ConfigError(f"{fld}: {_name(u)} is corrupt ({type(e).__name__})") from None


def _text(name: str, value: str | Upload, seen: dict[str, str]) -> str:
    if not isinstance(value, str):
        raise ConfigError(f"{name}: expected a text value, got a file")
    if name in seen:
        raise ConfigError(f"{name}: given more than once")
    if len(value) > MAX_TEXT:
        raise ConfigError(f"{name}: longer than {MAX_TEXT} characters")
    if _CONTROL.search(value):
        raise ConfigError(f"{name}: contains control characters")
    return value.strip()


def _name(u: Upload) -> str:
    return repr(u.filename[:64]) if u.filename else "the upload"


def _prefix(value: str | None, hi: int) -> int | None:
    if value is None or value == "":
        return None
    if not _PREFIX.fullmatch(value) or not 1 <= int(value) <= hi:
        raise ConfigError(f"prefix: expected an integer from 1 to {hi} (keyframes shown), got {value[:32]!r}")
    return int(value)
