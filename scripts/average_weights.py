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

import json
import shutil
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
    if len(w) != n or min(w) < 0 or abs(sum(w) - 1) > 1e-6:
        raise ConfigError(f"weights: {w} must be {n} non-negative numbers summing to 1")
    return w


def _checked(src: list[Path]) -> list[str]:
    """The safetensors files every checkpoint holds (names of the first's), after checking the configs agree."""
    for s in src:
        if not (s / "config.json").is_file():
            raise ConfigError(f"src: {s} is not a model folder (no config.json)")
    first = json.loads((src[0] / "config.json").read_text())
    for s in src[1:]:
        if json.loads((s / "config.json").read_text()) != first:
            raise ConfigError(f"src: {s}'s config.json differs from {src[0]}'s (not one architecture)")
    files = sorted(p.name for p in src[0].glob("*.safetensors"))
    if not files:
        raise ConfigError(f"src: {src[0]} has no .safetensors weights")
    for s in src[1:]:
        if missing := [f for f in files if not (s / f).is_file()]:
            raise ConfigError(f"src: {s} lacks {', '.join(missing)}")
    return files


def average_file(paths: list[Path], weights: list[float]) -> tuple[dict, dict[str, str] | None]:
    """The weighted mean of one safetensors file's tensors across checkpoints (float tensors averaged in float32 and
    cast back; any other tensor must be equal in all), and the first file's metadata."""
    import torch
    from safetensors import SafetensorError, safe_open

    try:
        loaded = [safe_open(str(p), framework="pt") for p in paths]
    except SafetensorError as e:
        raise ConfigError(f"src: unreadable weights among {', '.join(map(str, paths))}: {e}") from None
    meta, names = loaded[0].metadata(), list(loaded[0].keys())
    out = {}
    for name in names:
        ts = []
        for p, f in zip(paths, loaded, strict=True):
            if name not in f.keys():
                raise ConfigError(f"src: {p} has no tensor {name}")
            ts.append(f.get_tensor(name))
        if any(t.shape != ts[0].shape or t.dtype != ts[0].dtype for t in ts):
            raise ConfigError(f"src: tensor {name} differs in shape or dtype between {paths[0]} and the others")
        if ts[0].is_floating_point():
            out[name] = sum(w * t.float() for w, t in zip(weights, ts, strict=True)).to(ts[0].dtype).contiguous()
        elif all(torch.equal(t, ts[0]) for t in ts):
            out[name] = ts[0]
        else:
            raise ConfigError(f"src: non-float tensor {name} differs between checkpoints (cannot be averaged)")
    return out, meta


def main(argv: list[str]) -> int:
    cfg = load_config(DEFAULTS, argv)
    if not isinstance(cfg.out, str) or cfg.src is None or isinstance(cfg.src, str) or len(cfg.src) < 2:
        raise ConfigError("src/out: give two or more checkpoint folders and the output folder ('src=[A,B]' out=DIR)")
    src, out = [Path(str(s)) for s in cfg.src], Path(cfg.out)
    if out.exists():
        raise ConfigError(f"out: {out} already exists; nothing was written")
    weights = _weights(cfg.weights, len(src))
    files = _checked(src)
    from safetensors.torch import save_file

    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for f in files:
        tensors, meta = average_file([s / f for s in src], weights)
        save_file(tensors, str(tmp / f), metadata=meta)
    for p in src[0].iterdir():
        if p.is_file() and p.suffix != ".safetensors":
            shutil.copy2(p, tmp / p.name)
    (tmp / "averaged_from.json").write_text(json.dumps({"src": [str(s) for s in src], "weights": weights}, indent=1))
    tmp.rename(out)
    print(out)
    return 0


if __name__ == "__main__":
    cli_main(main, __doc__)
