"""Average the weights of checkpoints of one model (a linear "model soup"): every floating tensor is the weighted mean
of the checkpoints' tensors. For checkpoints on one fine-tuning path (a stage and the stage it started from) this is
WiSE-FT's interpolation, which keeps much of the later stage's gain and the earlier one's robustness off its data.

Run as:
    S=outputs/r15/rows
    python scripts/average_weights.py "src=[$S/rand3_tuned/final,$S/rand4_tuned/final]" out=$S/soup34/final
    python scripts/average_weights.py 'src=[A,B]' 'weights=[0.7,0.3]' out=DIR

Every *.safetensors file of the first checkpoint is averaged with the same file of the others (same tensor names,
shapes and dtypes; their config.json must agree); the first checkpoint's other files (config, processor, chat
template, labrobfail.json) are copied, its folders (benches) are not. The result is written to <out>.tmp and renamed,
so a failed run leaves no half-written model. (mergekit does this and much more for large LLMs; for one linear mean
of a checkpoint's own safetensors files it would be a large dependency for a few lines.)
"""

from __future__ import annotations

import contextlib
import json
import math
import shutil
from collections.abc import Sequence
from pathlib import Path

from labrobfail_vlm.config import ConfigError, cli_main, load_config

DEFAULTS = """
src: null                  # the checkpoint folders to average (two or more, one architecture)
weights: null              # one non-negative weight per checkpoint, summing to 1 (null: equal weights)
out: null                  # the folder to write (must not exist)
"""


def _weights(cfg_weights: object, n: int) -> list[float]:
    if cfg_weights is None:
        return [1.0 / n] * n
    try:
        w = [float(x) for x in cfg_weights]  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ConfigError(f"weights: {cfg_weights!r} is not a list of numbers") from None
    if len(w) != n or not all(math.isfinite(x) and x >= 0 for x in w) or abs(sum(w) - 1) > 1e-6:
        raise ConfigError(f"weights: {w} must be {n} non-negative numbers summing to 1")
    return w


def _checked(src: list[Path]) -> list[str]:
    """The safetensors files every checkpoint holds, after checking the folders agree: the same config.json, the same
    weight files, and for LabRobFail checkpoints whole-model tuning (a LoRA adapter's A and B matrices are not averaged
    apart: merge each with scripts/merge.py first) on the same grid."""
    for s in src:
        if not (s / "config.json").is_file():
            raise ConfigError(f"src: {s} has no config.json (a LoRA checkpoint: merge it with scripts/merge.py first)")
    first = json.loads((src[0] / "config.json").read_text())
    files = sorted(p.name for p in src[0].glob("*.safetensors"))
    if not files:
        raise ConfigError(f"src: {src[0]} has no .safetensors weights")
    card = [json.loads(f.read_text()) if (f := s / "labrobfail.json").is_file() else None for s in src]
    for s, c in zip(src, card, strict=True):
        if json.loads((s / "config.json").read_text()) != first:
            raise ConfigError(f"src: {s}'s config.json differs from {src[0]}'s (not one architecture)")
        if sorted(p.name for p in s.glob("*.safetensors")) != files:
            raise ConfigError(f"src: {s}'s .safetensors files differ from {src[0]}'s ({', '.join(files)})")
        if c is not None and c.get("tuning") != "full":
            raise ConfigError(f"src: {s} was tuned '{c.get('tuning')}', not 'full' (merge it with scripts/merge.py)")
        if (c or {}).get("grid") != (card[0] or {}).get("grid"):
            raise ConfigError(f"src: {s}'s grid (labrobfail.json) differs from {src[0]}'s")
    return files


def average_file(paths: list[Path], weights: list[float]) -> tuple[dict, dict[str, str] | None]:
    """The weighted mean of one safetensors file's tensors across checkpoints (float tensors averaged in float32 and
    cast back; any other tensor must be equal in all), and the first file's metadata."""
    from safetensors import SafetensorError, safe_open

    with contextlib.ExitStack() as stack:
        try:
            loaded = [stack.enter_context(safe_open(str(p), framework="pt")) for p in paths]
        except SafetensorError as e:
            raise ConfigError(f"src: unreadable weights among {', '.join(map(str, paths))}: {e}") from None
        meta, names = loaded[0].metadata(), sorted(loaded[0].keys())
        for p, f in zip(paths[1:], loaded[1:], strict=True):
            if sorted(f.keys()) != names:
                raise ConfigError(f"src: {p} holds other tensor names than {paths[0]}")
        return _mean(names, loaded, paths, weights), meta


def _mean(names: list[str], loaded: list, paths: list[Path], weights: list[float]) -> dict:
    import torch

    out = {}
    for name in names:
        ts = [f.get_tensor(name) for f in loaded]
        if any(t.shape != ts[0].shape or t.dtype != ts[0].dtype for t in ts):
            raise ConfigError(f"src: tensor {name} differs in shape or dtype between {paths[0]} and the others")
        if ts[0].is_floating_point():
            out[name] = sum(w * t.float() for w, t in zip(weights, ts, strict=True)).to(ts[0].dtype).contiguous()
        elif all(torch.equal(t, ts[0]) for t in ts):
            out[name] = ts[0]
        else:
            raise ConfigError(f"src: non-float tensor {name} differs between checkpoints (cannot be averaged)")
    return out


def main(argv: list[str]) -> int:
    cfg = load_config(DEFAULTS, argv)
    listed = isinstance(cfg.src, Sequence) and not isinstance(cfg.src, str)
    if not isinstance(cfg.out, str) or not listed or len(cfg.src) < 2:
        raise ConfigError("src/out: give two or more checkpoint folders and the output folder ('src=[A,B]' out=DIR)")
    src, out = [Path(str(s)) for s in cfg.src], Path(cfg.out)
    if out.exists():
        raise ConfigError(f"out: {out} already exists; nothing was written")
    weights = _weights(cfg.weights, len(src))
    files = _checked(src)
    from safetensors.torch import save_file

    from labrobfail_vlm.drawing import merge as merge_drawing
    from labrobfail_vlm.train.checkpoint import trained_drawing
    from labrobfail_vlm.train.resume import SETTINGS_FILE

    tmp = out.with_name(out.name + ".tmp")
    if tmp.exists():
        raise ConfigError(f"out: {tmp} exists (a run still going, or one to look at); nothing was written")
    tmp.mkdir(parents=True)
    try:
        for f in files:
            tensors, meta = average_file([s / f for s in src], weights)
            save_file(tensors, str(tmp / f), metadata=meta)
        for p in src[0].iterdir():
            if p.is_file() and p.suffix != ".safetensors" and p.name != SETTINGS_FILE:  # no one run's settings
                shutil.copy2(p, tmp / p.name)
        if (tmp / "labrobfail.json").is_file():  # what every source's grids drew, as one record
            man = json.loads((tmp / "labrobfail.json").read_text())
            drawn = merge_drawing([trained_drawing(s) for s in src])
            man = {k: v for k, v in man.items() if k != "drawing"} | ({"drawing": drawn} if drawn else {})
            (tmp / "labrobfail.json").write_text(json.dumps(man, indent=1))
        info = {"src": [str(s) for s in src], "weights": weights}
        (tmp / "averaged_from.json").write_text(json.dumps(info, indent=1))
    except BaseException:
        shutil.rmtree(tmp)  # a failed or interrupted run leaves nothing half-written
        raise
    tmp.rename(out)
    print(out)
    return 0


if __name__ == "__main__":
    cli_main(main, __doc__)
