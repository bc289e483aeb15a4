"""Shared fixtures of the service tests: a tiny Qwen3-VL whose Q2 verdict depends on the grid, and grids of
both verdicts (so batched decoding is tested on the failure path too: Q3-Q6 decoded for some rows only)."""

import numpy as np
import pytest
from PIL import Image

TASKS = ["pick up the small beaker", "press the red button", "open the oven door"]


@pytest.fixture(scope="session")
def mixed_model(tmp_path_factory):
    """The tiny random model with its "Yes" and "No" output rows swapped: it then answers Q2 "Yes" for grids of
    random keyframes and "No" for plain bright grids (measured), instead of "No" for everything."""
    import torch

    from labrobfail_vlm.model.loading import load_model, load_processor
    from labrobfail_vlm.model.tiny import build_tiny

    out = build_tiny(tmp_path_factory.mktemp("mixed") / "tiny")
    model, tok = load_model(out), load_processor(out).tokenizer
    yes, no = (tok.convert_tokens_to_ids(w) for w in ("Yes", "No"))
    with torch.no_grad():
        w = model.lm_head.weight
        w[[yes, no]] = w[[no, yes]].clone()
    model.save_pretrained(out, safe_serialization=True)
    return out


def frame_lists(seed, views=2, frames=8, side=64):
    rng = np.random.default_rng(seed)
    return [[rng.integers(0, 255, (side, side, 3), dtype=np.uint8) for _ in range(frames)] for _ in range(views)]


@pytest.fixture(scope="session")
def grids():
    """Six 256x128 grids (three of random keyframes: "Yes"; three plain: "No") and two 512x256 ones."""
    from labrobfail_vlm.analyzer import frames_to_grid
    from labrobfail_vlm.grid import GridConfig

    small = GridConfig(width=256, height=128, max_frames=8, columns=4)
    out = [frames_to_grid(frame_lists(s), small) for s in range(3)]
    out += [Image.new("RGB", (256, 128), (v, v, v)) for v in (128, 200, 255)]
    out += [
        frames_to_grid(frame_lists(9), GridConfig(width=512, height=256, max_frames=8, columns=4)),
        Image.new("RGB", (512, 256), (200, 200, 200)),
    ]
    return out
