"""Fine-tuned checkpoints: LoRA adapter (peft) + fully trained vision/merger weights + a small manifest.

Layout of a checkpoint directory:
  adapter_config.json, adapter_model.safetensors   the decoder's LoRA (peft format)
  vision_merger.safetensors                        model.visual.* weights (hybrid mode)
  model.safetensors + config.json                  full weights instead (full mode)
  labrobfail.json                                  {"base_model": DIR, "tuning": mode, "grid": {...},
                                                   "drawing": {...} (labrobfail_vlm/drawing.py)}
  processor files                                  tokenizer, chat template, image processor
`load_finetuned` rebuilds the model from the base directory; scripts/merge.py writes a standalone model.
`validate_checkpoint` checks any model directory (base, merged or fine-tuned) before a tensor is built: the one
check infer.py, labrobfail-serve and FailureAnalyzer.from_pretrained (the VLM supervisor) go through.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file

from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.grid import GridConfig
from labrobfail_vlm.io import atomic_write_json
from labrobfail_vlm.model.hybrid import MODES, group_of
from labrobfail_vlm.model.loading import (
    ModelCheck,
    Shapes,
    check_model_dir,
    match_shapes,
    safetensors_header,
    validate_model_dir,
)

MANIFEST = "labrobfail.json"
VISION_FILE = "vision_merger.safetensors"
ADAPTER_FILE = "adapter_model.safetensors"
_PEFT_PREFIX = "base_model.model."
# a saved LoRA weight: base_model.model.<module>.lora_A|lora_B[.<adapter name>].weight
_LORA = re.compile(r"base_model\.model\.(?P<module>.+)\.lora_(?P<ab>[AB])(?:\.[^.]+)?\.weight")


def save_trainable(
    model: Any,
    out: Path,
    state_dict: dict[str, torch.Tensor],
    base_model: str,
    tuning: str,
    grid: dict[str, Any] | None = None,
    drawing: dict[str, Any] | None = None,
) -> None:
    """Write adapter + vision/merger (or full) weights from a state dict gathered on every rank.

    `grid` is the dataset's grid config; inference builds its grids (and bounds Q3) the same way. `drawing`: what
    the simulator drew into the training grids (labrobfail_vlm/drawing.py), checked by labrobfail-supervise.
    """
    out.mkdir(parents=True, exist_ok=True)
    # Full model: every weight. PeftModel: it keeps only the lora_ keys of the state dict.
    model.save_pretrained(out, state_dict=state_dict, safe_serialization=True)
    if tuning == "hybrid":  # the fully trained vision encoder and merger, under the base model's names
        vis = {
            k.removeprefix(_PEFT_PREFIX): v.detach().cpu().contiguous()
            for k, v in state_dict.items()
            if group_of(k) in ("vision", "merger")
        }
        save_file(vis, str(out / VISION_FILE), metadata={"format": "pt"})
    manifest = {"base_model": str(base_model), "tuning": tuning, "grid": grid}
    atomic_write_json(out / MANIFEST, manifest | ({"drawing": drawing} if drawing is not None else {}))


def is_finetuned(path: str | Path) -> bool:
    return (Path(path) / MANIFEST).is_file()


def trained_grid(path: str | Path) -> GridConfig | None:
    """The grid config a checkpoint was trained on (None for a base model or an older checkpoint)."""
    try:
        grid = json.loads((Path(path) / MANIFEST).read_text()).get("grid")
    except (OSError, ValueError, AttributeError):
        return None
    if not isinstance(grid, dict):
        return None
    return GridConfig.from_dict(grid)


def trained_drawing(path: str | Path) -> dict[str, Any] | None:
    """What the simulator drew into a checkpoint's training grids (None: not recorded, or not a fine-tuned one)."""
    try:
        drawing = json.loads((Path(path) / MANIFEST).read_text()).get("drawing")
    except (OSError, ValueError, AttributeError):
        return None
    return drawing if isinstance(drawing, dict) else None


def last_complete_checkpoint(output_dir: str | Path) -> tuple[Path | None, list[Path]]:
    """The newest `checkpoint-N` of a run that was fully written, and the newer ones that were not.

    transformers writes a checkpoint's trainer_state.json last, so a run killed while saving leaves a folder
    without it (or with it cut short); `get_last_checkpoint` would pick that folder and the resume would fail
    half-way through loading. A checkpoint counts as complete when its trainer_state.json parses and names step N.
    """
    found = []
    for d in Path(output_dir).glob("checkpoint-*"):
        if d.is_dir() and (m := re.fullmatch(r"checkpoint-(\d+)", d.name)):
            found.append((int(m[1]), d))
    skipped: list[Path] = []
    for step, d in sorted(found, reverse=True):
        try:
            state = json.loads((d / "trainer_state.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            state = None
        if isinstance(state, dict) and state.get("global_step") == step:
            return d, skipped
        skipped.append(d)
    return None, skipped


def read_manifest(p: Path, field: str) -> dict[str, Any]:
    """labrobfail.json as a dict with a known `tuning` (and a `base_model` unless the weights are all here)."""
    f = p / MANIFEST
    try:
        man = json.loads(f.read_text(encoding="utf-8"))
    except OSError as e:
        raise ConfigError(f"{field}: cannot read {f} ({e.strerror or type(e).__name__})") from None
    except (ValueError, RecursionError):
        raise ConfigError(f"{field}: {f} is not valid JSON") from None
    if not isinstance(man, dict):
        raise ConfigError(f"{field}: {f} holds a JSON {type(man).__name__}, expected an object")
    if man.get("tuning") not in MODES:
        raise ConfigError(f"{field}: {f} has tuning {man.get('tuning')!r}; expected one of {', '.join(MODES)}")
    if man["tuning"] != "full" and not (isinstance(man.get("base_model"), str) and man["base_model"]):
        raise ConfigError(f"{field}: {f} names no base_model directory (needed for tuning {man['tuning']!r})")
    return man


def _json_object(f: Path, field: str) -> None:
    try:
        ok = isinstance(json.loads(f.read_text(encoding="utf-8")), dict)
    except OSError as e:
        raise ConfigError(f"{field}: cannot read {f} ({e.strerror or type(e).__name__})") from None
    except (ValueError, RecursionError):
        ok = False
    if not ok:
        raise ConfigError(f"{field}: {f} is not a JSON object")


def check_adapter(adapter: Shapes, base: Shapes, f: Path, field: str) -> None:
    """Each LoRA pair must fit the base weight it adapts: lora_A is (r, in), lora_B (out, r)."""
    ranks: dict[str, dict[str, int]] = {}
    for name, shape in adapter.items():
        m = _LORA.fullmatch(name)
        target = f"{m['module']}.weight" if m else ""
        if m is None or target not in base or len(shape) != 2:
            raise ConfigError(
                f"{field}: {f}: tensor {name[:120]!r} is not a LoRA weight of a base model layer "
                f"(an adapter for another model?)"
            )
        out_f, in_f = base[target][0], base[target][-1]
        if (m["ab"] == "A" and shape[1] != in_f) or (m["ab"] == "B" and shape[0] != out_f):
            raise ConfigError(
                f"{field}: {f}: {name} has shape {list(shape)}, which does not fit the base weight "
                f"{target} {list(base[target])} (an adapter for another base model?)"
            )
        ranks.setdefault(m["module"], {})[m["ab"]] = shape[0] if m["ab"] == "A" else shape[1]
    for module, r in ranks.items():
        if len(set(r.values())) != 1 or len(r) != 2:
            raise ConfigError(f"{field}: {f}: the LoRA pair of {module} is incomplete or its ranks differ ({r})")


def validate_checkpoint(
    path: str | Path, field: str = "model.path", max_gb: float | None = None, dtype: Any = None
) -> ModelCheck:
    """Refuse, with one line, any model directory that cannot load as a supported Qwen3-VL within the memory
    budget, before a tensor is built: a base or merged model (labrobfail_vlm.model.loading.validate_model_dir),
    or a fine-tuned checkpoint (its manifest, adapter and vision weights, and the base they point at)."""
    p = Path(path)
    if not p.is_dir():
        raise ConfigError(f"{field}: no such model directory {str(path)!r}")
    if not is_finetuned(p):
        return validate_model_dir(p, field, max_gb, dtype)
    man = read_manifest(p, field)
    if man["tuning"] == "full":  # every weight is in the checkpoint itself
        return validate_model_dir(p, field, max_gb, dtype)
    check_model_dir(p, field, weights=False)  # the processor travels with the checkpoint
    _json_object(p / "adapter_config.json", field)
    if not (p / ADAPTER_FILE).is_file():
        raise ConfigError(f"{field}: {path} lacks {ADAPTER_FILE}")
    adapter = safetensors_header(p / ADAPTER_FILE, field)
    extra = sum(math.prod(s) for s in adapter.values())
    base = validate_model_dir(man["base_model"], f"{field} (base_model of {p / MANIFEST})", max_gb, dtype, extra)
    check_adapter(adapter, base.shapes, p / ADAPTER_FILE, field)
    if man["tuning"] == "hybrid":  # trained vision/merger weights replace the base's: same names and shapes
        if not (p / VISION_FILE).is_file():
            raise ConfigError(f"{field}: {path} lacks {VISION_FILE}")
        vision = {k: s for k, s in base.shapes.items() if group_of(k) in ("vision", "merger")}
        match_shapes(safetensors_header(p / VISION_FILE, field), vision, str(p / VISION_FILE), field, optional=vision)
    return base


def load_finetuned(path: str | Path, dtype: Any = None, max_gb: float | None = None):
    """Base model + adapter + vision weights, ready for inference (LoRA not merged). Validated first (see
    validate_checkpoint; `max_gb`: the model memory budget)."""
    from labrobfail_vlm.model.loading import load_model

    p = Path(path)
    validate_checkpoint(p, "model.path", max_gb, dtype)
    man = read_manifest(p, "model.path")
    if man["tuning"] == "full":
        return load_model(p, dtype, max_gb)
    from peft import PeftModel

    base = load_model(man["base_model"], dtype, max_gb)
    if man["tuning"] == "hybrid":
        missing, unexpected = base.load_state_dict(load_file(str(p / VISION_FILE)), strict=False)
        if unexpected:
            raise ConfigError(f"model: {VISION_FILE} has unknown weights, e.g. {unexpected[0]}")
    return PeftModel.from_pretrained(base, str(p), is_trainable=False)
