"""Write one keyframe strip per failure type and four random successes from generated shards, to look at.

Run as:
    python scripts/render_strips.py shards=outputs/demo_shards out=outputs/demo_strips

Each PNG shows the failure episode's keyframes (rows = camera views) with the
keyframe index in each cell and a red frame on the labeled failure keyframe,
above its paired success episode.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
from PIL import Image, ImageDraw

from labrobfail_vlm.config import ConfigError, cli_main, load_config
from labrobfail_vlm.io import save_image
from labrobfail_vlm.taxonomy import FAILURE_TYPE_NAMES

DEFAULTS = """
shards: outputs/demo_shards   # a shard folder from labrobfail-generate
out: outputs/demo_strips      # where the strips go
"""


CELL = 128  # px: cells are shown at most this wide (a 50-keyframe strip at 192 px would be 9,600 px wide)


def strip(row: dict, mark: int | None) -> Image.Image:
    # Keyframes the generator did not render (render_frames) hold b"" and are left out; cells keep their number.
    shown = [c for c, b in enumerate(row["images"][0]) if b]
    views = [[Image.open(io.BytesIO(v[c])).convert("RGB") for c in shown] for v in row["images"]]
    views = [[im.resize((CELL, CELL)) if im.width > CELL else im for im in v] for v in views]
    w, h = views[0][0].size
    n = len(views[0])
    if mark is not None:  # the failure shows in the first image taken at or after its keyframe
        mark = next((kf for kf in shown if kf >= mark), shown[-1])
    out = Image.new("RGB", (w * n, h * len(views) + 18), "white")
    d = ImageDraw.Draw(out)
    d.text(
        (4, 3),
        f"{row['scenario']} | {row['role']} | success={row['success']} | {row['failure_type'] or ''} "
        f"| failure keyframe={row['failure_keyframe']}",
        fill="black",
    )
    for r, v in enumerate(views):
        for c, (kf, img) in enumerate(zip(shown, v)):
            out.paste(img, (c * w, 18 + r * h))
            d.text((c * w + 3, 18 + r * h + 2), str(kf), fill="black")
            if mark is not None and kf == mark:
                d.rectangle([c * w, 18 + r * h, (c + 1) * w - 1, 18 + (r + 1) * h - 1], outline="red", width=3)
    return out


def main(argv: list[str]) -> int:
    cfg = load_config(DEFAULTS, argv)
    shards, out_dir = str(cfg.shards), str(cfg.out)
    if not Path(shards).is_dir():
        raise ConfigError(f"shards: no such directory {shards!r}")
    rows = []
    for p in sorted(Path(shards).glob("shard-*.parquet")):
        rows.extend(pq.read_table(p).to_pylist())
    if not rows:
        raise ConfigError(f"shards: no shard-*.parquet files in {shards}")
    by_pair = {}
    for r in rows:
        by_pair.setdefault(r["pair_id"], {})[r["role"]] = r
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = 0
    for ftype in FAILURE_TYPE_NAMES:
        hit = next((r for r in rows if r["failure_type"] == ftype and r["role"] == "injected"), None) or next(
            (r for r in rows if r["failure_type"] == ftype), None
        )
        if hit is None:
            continue
        a = strip(hit, hit["failure_keyframe"])
        twin = by_pair[hit["pair_id"]].get("nominal" if hit["role"] == "injected" else "injected")
        if twin is not None:
            b = strip(twin, twin["failure_keyframe"])
            canvas = Image.new("RGB", (max(a.width, b.width), a.height + b.height + 6), "white")
            canvas.paste(a, (0, 0))
            canvas.paste(b, (0, a.height + 6))
            a = canvas
        save_image(a, out / f"{ftype}.png")
        written += 1
    successes = [r for r in rows if r["success"]]
    rng = np.random.default_rng(0)
    for k, i in enumerate(rng.choice(len(successes), size=min(4, len(successes)), replace=False)):
        save_image(strip(successes[int(i)], None), out / f"success_{k}.png")
        written += 1
    print(f"wrote {written} strips to {out}")
    return 0


if __name__ == "__main__":
    cli_main(main, __doc__)
