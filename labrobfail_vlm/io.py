"""Atomic file output (temp file + fsync + rename): a killed run never leaves a half-written file; the resume points
of a resumable run (what they hold beside the weights, and the newest complete one)."""

from __future__ import annotations

import hashlib
import json
import os
import secrets
from pathlib import Path
from typing import Any


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """`data` into `path` whole or not at all. The temp file's name is this call's own (processes that write the same
    file together never write into one temp file), and a write that fails (disk full) takes its temp file with it."""
    path = Path(path)
    tmp = path.with_name(f"{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    try:
        with open(tmp, "xb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def append_line(path: Path, line: str) -> None:
    """`line` (no newline) added to the end of a line log in one O_APPEND write: processes appending to the same log
    at once keep every line (a read and rewrite would drop another's), and a kill loses at most this line."""
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(fd, (line + "\n").encode())
        os.fsync(fd)
    finally:
        os.close(fd)


def swap_in(tmp: Path, final: Path) -> None:
    """The fully written folder `tmp` in place of `final` (a model, a resume point): a reader finds the old folder or
    the new one whole, never a mix. A kill between the two renames leaves `<final>.old` and no `final`; `swapped`
    reads it back."""
    import shutil

    old = final.with_name(final.name + ".old")
    if final.exists():  # else `old` may be the only whole copy (a kill between renames): it goes after the swap
        shutil.rmtree(old, ignore_errors=True)
        final.rename(old)
    tmp.rename(final)
    shutil.rmtree(old, ignore_errors=True)


def swapped(final: Path, marker: str) -> Path:
    """`final`, or the `<final>.old` a kill in the middle of `swap_in` left, whichever holds `marker`."""
    old = final.with_name(final.name + ".old")
    return old if not (final / marker).is_file() and (old / marker).is_file() else final


def sha256_file(path: Path) -> str:
    """A file's sha256 (hex), read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def atomic_write_json(path: Path, obj: Any, indent: int = 1) -> None:
    atomic_write_bytes(Path(path), json.dumps(obj, indent=indent, ensure_ascii=False).encode())


def newest_complete(root: Path, prefix: str, marker: str) -> Path | None:
    """The `prefix-N` folder under `root` with the largest N whose `marker` file exists, or None. A resumable run
    writes the marker last into each state folder it saves, so a folder without it was cut short."""
    done = [d for d in Path(root).glob(f"{prefix}-*") if d.name[len(prefix) + 1 :].isdigit() and (d / marker).is_file()]
    return max(done, key=lambda d: int(d.name[len(prefix) + 1 :])) if done else None


RESUME_TENSORS = "optim.pt"  # beside a resumable run's weights: optimizer, schedule, RNG states (plain tensors)


def save_resume_state(folder: Path, tensors: dict[str, Any], state: dict[str, Any], marker: str) -> None:
    """The rest of a resume point whose weights are already in `folder`: `tensors` (optim.pt), then `state` as the
    JSON `marker`, written last, so `newest_complete` never picks a folder a kill cut short."""
    import torch

    (folder / marker).unlink(missing_ok=True)  # a folder reused from an earlier run: not complete until the end
    torch.save(tensors, folder / RESUME_TENSORS)
    atomic_write_json(folder / marker, state)


def load_resume_state(folder: Path, marker: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """What `save_resume_state` wrote: the tensors (read with weights_only=True, so no pickled code runs) and state."""
    import torch

    return torch.load(folder / RESUME_TENSORS, weights_only=True), json.loads((folder / marker).read_text())


def save_image(img: Any, path: Path, **options: Any) -> None:
    """A PIL image written whole or not at all, in the format its suffix names (`options`: the encoder's)."""
    import io

    buf = io.BytesIO()
    img.save(buf, format=Path(path).suffix.lstrip(".").upper().replace("JPG", "JPEG"), **options)
    atomic_write_bytes(Path(path), buf.getvalue())


def save_figure(fig: Any, path: Path, dpi: int = 110) -> None:
    """Save a matplotlib figure as PNG atomically and close it."""
    import io

    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, dpi=dpi, format="png")
    plt.close(fig)
    atomic_write_bytes(Path(path), buf.getvalue())


def write_report(path: str | Path, obj: Any) -> int:
    """A benchmark's result written atomically as JSON (its folder made) and printed; 0, the exit code."""
    out = Path(str(path))
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out, obj)
    print(json.dumps(obj, indent=1))
    return 0
