"""Atomic file output (temp file + fsync + rename): a killed run never leaves a half-written file; the newest
complete state folder of a resumable run."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any


def atomic_write_bytes(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def atomic_write_json(path: Path, obj: Any, indent: int = 1) -> None:
    atomic_write_bytes(Path(path), json.dumps(obj, indent=indent, ensure_ascii=False).encode())


def newest_complete(root: Path, prefix: str, marker: str) -> Path | None:
    """The `prefix-N` folder under `root` with the largest N whose `marker` file exists, or None. A resumable run
    writes the marker last into each state folder it saves, so a folder without it was cut short."""
    done = [d for d in Path(root).glob(f"{prefix}-*") if d.name[len(prefix) + 1 :].isdigit() and (d / marker).is_file()]
    return max(done, key=lambda d: int(d.name[len(prefix) + 1 :])) if done else None


def save_figure(fig: Any, path: Path, dpi: int = 110) -> None:
    """Save a matplotlib figure as PNG atomically and close it."""
    import matplotlib.pyplot as plt

    tmp = path.with_name(path.stem + ".tmp.png")
    fig.tight_layout()
    fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    tmp.replace(path)
