"""Load Qwen3-VL and its processor from a local directory: safetensors only, no remote code, no hub.

A real checkpoint (e.g. Qwen3-VL-8B-Instruct downloaded elsewhere) and the tiny preset go
through this same function. A missing or incomplete directory is a one-line ConfigError.

Before any tensor is built, `validate_model_dir` checks what transformers would otherwise trust blindly:
config.json must be a JSON object naming Qwen3-VL (model_type `qwen3_vl`, architectures
`[Qwen3VLForConditionalGeneration]`); the parameter count implied by the config must fit the memory budget
(a `{}` config silently becomes the default ~12.6 B-parameter model, ~50 GB in float32); and the safetensors
files must be complete (file length = header + the header's tensor offsets) and hold exactly the tensor names
and shapes the config implies. Fine-tuned checkpoints (labrobfail.json + adapter) are checked by
`labrobfail_vlm.train.checkpoint.validate_checkpoint`, which uses these functions on their base.

The memory budget: the `max_gb` argument (`max_model_gb` of infer.py / labrobfail-serve), else
$LABROBFAIL_MAX_MODEL_GB, else half of this machine's memory (its cgroup limit when that is lower).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

from labrobfail_vlm.config import ConfigError

ARCHITECTURE = "Qwen3VLForConditionalGeneration"
MODEL_TYPE = "qwen3_vl"
BUDGET_ENV = "LABROBFAIL_MAX_MODEL_GB"
INDEX_FILE = "model.safetensors.index.json"
MAX_CONFIG_BYTES = 16 << 20  # a real config.json is a few KB; a huge one is not a config
MAX_HEADER_BYTES = 100 << 20  # the safetensors library's own header limit
# bytes per element of every safetensors dtype (the format's spec)
DTYPE_BYTES = {
    "BOOL": 1,
    "U8": 1,
    "I8": 1,
    "F8_E4M3": 1,
    "F8_E5M2": 1,
    "F8_E8M0": 1,
    "I16": 2,
    "U16": 2,
    "F16": 2,
    "BF16": 2,
    "I32": 4,
    "U32": 4,
    "F32": 4,
    "I64": 8,
    "U64": 8,
    "F64": 8,
    "C64": 8,
}
Shapes = dict[str, tuple[int, ...]]


@dataclass(frozen=True)
class ModelCheck:
    """What validation learnt: `shapes` are the tensors the config implies (name -> shape)."""

    path: Path
    params: int
    bytes: int  # the weights' size in the dtype they are loaded in
    budget: int
    shapes: Shapes


def check_model_dir(path: str | Path, field: str = "model.path", weights: bool = True) -> Path:
    p = Path(path)
    if not p.is_dir():
        raise ConfigError(f"{field}: no such model directory {str(path)!r}")
    if not ((p / "tokenizer.json").is_file() or (p / "tokenizer_config.json").is_file()):
        raise ConfigError(f"{field}: {path} has no tokenizer files")
    if not weights:
        return p
    if not (p / "config.json").is_file():
        raise ConfigError(f"{field}: {path} has no config.json (not a Hugging Face model directory)")
    if not list(p.glob("*.safetensors")) and not (p / INDEX_FILE).is_file():
        bins = list(p.glob("*.bin")) + list(p.glob("*.pt"))
        raise ConfigError(
            f"{field}: {path} has no .safetensors weights" + (" (pickle weights are refused)" if bins else "")
        )
    return p


# ---- memory budget ----------------------------------------------------------------------------------------
def machine_memory() -> int:
    """Bytes of RAM this process can have: the machine's, or its cgroup's limit when lower (a container)."""
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    for f in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            limit = Path(f).read_text().strip()
        except OSError:
            continue
        if limit.isdigit():  # "max" = no limit
            total = min(total, int(limit))
    return total


def model_budget(max_gb: float | None = None) -> int:
    """Bytes the weights may take: `max_gb` (GB = 1e9 bytes), else $LABROBFAIL_MAX_MODEL_GB, else half the memory
    (the other half is for activations, images, the processor and everything else the process holds)."""
    where = "max_model_gb"
    if max_gb is None and os.environ.get(BUDGET_ENV, "").strip():
        where, text = f"${BUDGET_ENV}", os.environ[BUDGET_ENV].strip()
        try:
            max_gb = float(text)
        except ValueError:
            raise ConfigError(f"{where}: expected a number of GB, got {text[:32]!r}") from None
    if max_gb is None:
        return machine_memory() // 2
    if not math.isfinite(max_gb) or max_gb <= 0:
        raise ConfigError(f"{where}: expected a positive number of GB, got {max_gb!r}")
    return int(max_gb * 1e9)


def human_bytes(n: int) -> str:
    return f"{n / 1e9:.1f} GB" if n >= 1e9 else f"{n / 1e6:.1f} MB"


def element_bytes(dtype: Any) -> int:
    """Bytes per parameter once loaded: the loader's default is float32; "auto" or unknown counts as float32."""
    size = getattr(dtype, "itemsize", None)
    return int(size) if isinstance(size, int) and size > 0 else 4


# ---- config.json -------------------------------------------------------------------------------------------
def read_config(path: Path, field: str) -> dict[str, Any]:
    """config.json as a dict that names the supported Qwen3-VL; anything else is a one-line ConfigError."""
    f = path / "config.json"
    try:
        if f.stat().st_size > MAX_CONFIG_BYTES:
            raise ConfigError(f"{field}: {f} is {f.stat().st_size:,} bytes, too large for a model config")
        cfg = json.loads(f.read_text(encoding="utf-8"))
    except ConfigError:
        raise
    except OSError as e:
        raise ConfigError(f"{field}: cannot read {f} ({e.strerror or type(e).__name__})") from None
    except (ValueError, RecursionError) as e:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        where = f"line {e.lineno}" if hasattr(e, "lineno") else type(e).__name__
        raise ConfigError(f"{field}: {f} is not valid JSON ({where})") from None
    if not isinstance(cfg, dict):
        raise ConfigError(f"{field}: {f} holds a JSON {type(cfg).__name__}, expected an object")
    if cfg.get("model_type") != MODEL_TYPE:
        raise ConfigError(f"{field}: {f} has {_key(cfg, 'model_type')}; supported: {MODEL_TYPE!r} (Qwen3-VL)")
    if cfg.get("architectures") != [ARCHITECTURE]:
        raise ConfigError(f"{field}: {f} has {_key(cfg, 'architectures')}; supported: [{ARCHITECTURE!r}]")
    return cfg


def _key(cfg: dict[str, Any], key: str) -> str:
    return f"{key} {_short(cfg[key])}" if key in cfg else f"no {key}"


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def qwen3vl_config(cfg: dict[str, Any], f: Path, field: str) -> Any:
    """The transformers config object (cheap: no tensors), so defaults are exactly the ones the model would use."""
    from transformers import Qwen3VLConfig

    try:
        return Qwen3VLConfig.from_dict(cfg)
    except Exception as e:  # noqa: BLE001 - strict-dataclass validation raises several types; all mean "bad config"
        detail = " ".join(line.strip() for line in str(e).splitlines() if line.strip())[:200]
        raise ConfigError(f"{field}: {f} is not a valid Qwen3-VL config ({detail or type(e).__name__})") from None


def _dims(section: Any, prefix: str, names: Iterable[str], f: Path, field: str) -> list[int]:
    """Positive integer sizes of a config section, or a ConfigError naming the key (a bad size would otherwise
    surface as a shape error deep inside the model, or as an absurd allocation)."""
    out = []
    for name in names:
        v = getattr(section, name, None)
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ConfigError(f"{field}: {f}: {prefix}.{name} must be a positive integer, got {_short(v)}")
        out.append(v)
    return out


def expected_tensors(cfg: Any, f: Path = Path("config.json"), field: str = "model.path") -> Shapes:
    """Every tensor Qwen3VLForConditionalGeneration(cfg) saves, name -> shape, derived from the config alone
    (vision tower, mergers, text embeddings, decoder layers, lm_head unless tied). The parameter count is the sum
    of their sizes. tests/test_checkpoint_guard.py checks it against the real class built on the meta device."""
    t, v = cfg.text_config, cfg.vision_config
    hid, inter, hd, vocab, layers, heads, kvh = _dims(
        t,
        "text_config",
        (
            "hidden_size",
            "intermediate_size",
            "head_dim",
            "vocab_size",
            "num_hidden_layers",
            "num_attention_heads",
            "num_key_value_heads",
        ),
        f,
        field,
    )
    vh, vi, depth, ch, tp, ps, merge, out_h, npos = _dims(
        v,
        "vision_config",
        (
            "hidden_size",
            "intermediate_size",
            "depth",
            "in_channels",
            "temporal_patch_size",
            "patch_size",
            "spatial_merge_size",
            "out_hidden_size",
            "num_position_embeddings",
        ),
        f,
        field,
    )
    deepstack = getattr(v, "deepstack_visual_indexes", None) or ()
    q, kv, merged = heads * hd, kvh * hd, vh * merge**2
    out: Shapes = {"model.language_model.embed_tokens.weight": (vocab, hid), "model.language_model.norm.weight": (hid,)}
    for i in range(layers):
        p = f"model.language_model.layers.{i}."
        for name, shape in {"q_proj": (q, hid), "k_proj": (kv, hid), "v_proj": (kv, hid), "o_proj": (hid, q)}.items():
            out[f"{p}self_attn.{name}.weight"] = shape
            if getattr(t, "attention_bias", False):
                out[f"{p}self_attn.{name}.bias"] = (shape[0],)
        out.update(
            {
                f"{p}mlp.gate_proj.weight": (inter, hid),
                f"{p}mlp.up_proj.weight": (inter, hid),
                f"{p}mlp.down_proj.weight": (hid, inter),
                f"{p}self_attn.q_norm.weight": (hd,),
                f"{p}self_attn.k_norm.weight": (hd,),
                f"{p}input_layernorm.weight": (hid,),
                f"{p}post_attention_layernorm.weight": (hid,),
            }
        )
    if not getattr(cfg, "tie_word_embeddings", False):
        out["lm_head.weight"] = (vocab, hid)

    def linear(name: str, o: int, i: int) -> None:  # the vision tower's linears all carry a bias
        out[f"{name}.weight"], out[f"{name}.bias"] = (o, i), (o,)

    def layer_norm(name: str, n: int) -> None:
        out[f"{name}.weight"], out[f"{name}.bias"] = (n,), (n,)

    out["model.visual.patch_embed.proj.weight"] = (vh, ch, tp, ps, ps)
    out["model.visual.patch_embed.proj.bias"] = (vh,)
    out["model.visual.pos_embed.weight"] = (npos, vh)
    for i in range(depth):
        p = f"model.visual.blocks.{i}."
        layer_norm(p + "norm1", vh)
        layer_norm(p + "norm2", vh)
        linear(p + "attn.qkv", 3 * vh, vh)
        linear(p + "attn.proj", vh, vh)
        linear(p + "mlp.linear_fc1", vi, vh)
        linear(p + "mlp.linear_fc2", vh, vi)
    # the main merger normalises before the 2x2 shuffle, the deepstack mergers after it
    for p, norm in [("model.visual.merger.", vh)] + [
        (f"model.visual.deepstack_merger_list.{k}.", merged) for k in range(len(deepstack))
    ]:
        layer_norm(p + "norm", norm)
        linear(p + "linear_fc1", merged, merged)
        linear(p + "linear_fc2", out_h, merged)
    return out


def count_params(shapes: Shapes) -> int:
    return sum(math.prod(s) for s in shapes.values())


# ---- safetensors -------------------------------------------------------------------------------------------
def safetensors_header(f: Path, field: str) -> Shapes:
    """Tensor name -> shape from a safetensors file's header, after checking that the file is complete: its length
    must be 8 + header + the end of the last tensor's data (a shorter file is truncated). Reads the header only."""
    try:
        size = f.stat().st_size
        with open(f, "rb") as fh:
            head = fh.read(8)
            n = int.from_bytes(head, "little") if len(head) == 8 else -1
            if n < 2 or n > MAX_HEADER_BYTES or 8 + n > size:
                raise ConfigError(
                    f"{field}: {f} is truncated or not a safetensors file ({size:,} bytes, header length {n:,})"
                )
            meta = json.loads(fh.read(n))
    except ConfigError:
        raise
    except OSError as e:
        raise ConfigError(f"{field}: cannot read {f} ({e.strerror or type(e).__name__})") from None
    except (ValueError, RecursionError):
        raise ConfigError(f"{field}: {f} has a corrupt safetensors header (not JSON)") from None
    if not isinstance(meta, dict):
        raise ConfigError(f"{field}: {f} has a corrupt safetensors header (not a JSON object)")
    shapes: Shapes = {}
    spans: list[tuple[int, int, str]] = []
    for name, info in meta.items():
        if name == "__metadata__":
            continue
        shape, span = _tensor_entry(info)
        if shape is None or span is None:
            raise ConfigError(f"{field}: {f}: tensor {_short(name)} has a corrupt header entry")
        shapes[name] = shape
        spans.append((*span, name))
    end = 0
    for start, stop, name in sorted(spans):  # the format stores tensors back to back: a gap or overlap is corrupt
        if start != end:
            raise ConfigError(f"{field}: {f}: tensor {_short(name)} does not follow the previous one (corrupt)")
        end = stop
    data = size - 8 - n
    if end > data:
        raise ConfigError(
            f"{field}: {f} is truncated: its header needs {end:,} bytes of tensor data, the file holds {data:,}"
        )
    if end < data:
        raise ConfigError(f"{field}: {f} has {data - end:,} bytes after its last tensor (corrupt)")
    return shapes


def _tensor_entry(info: Any) -> tuple[tuple[int, ...] | None, tuple[int, int] | None]:
    """(shape, (start, stop)) of one header entry, or Nones when it is malformed or its size disagrees."""
    if not isinstance(info, dict) or info.get("dtype") not in DTYPE_BYTES:
        return None, None
    shape, offs = info.get("shape"), info.get("data_offsets")
    if not _naturals(shape) or not _naturals(offs) or len(offs) != 2:
        return None, None
    if offs[1] - offs[0] != math.prod(shape) * DTYPE_BYTES[info["dtype"]]:
        return None, None
    return tuple(shape), (offs[0], offs[1])


def _naturals(xs: Any) -> bool:
    return isinstance(xs, list) and all(isinstance(x, int) and not isinstance(x, bool) and x >= 0 for x in xs)


def weight_tensors(p: Path, field: str) -> tuple[Shapes, str]:
    """Every tensor of a model directory (model.safetensors, or the shards its index names) and how to name the
    weights in messages. A tensor the index puts in one shard but another shard holds is refused: transformers
    reads it from the shard the index names."""
    index = p / INDEX_FILE
    if not index.is_file():
        single = p / "model.safetensors"
        if not single.is_file():
            raise ConfigError(f"{field}: {p} has no model.safetensors (nor {INDEX_FILE})")
        return safetensors_header(single, field), str(single)
    try:
        wmap = json.loads(index.read_text(encoding="utf-8")).get("weight_map")
    except (OSError, ValueError, AttributeError, RecursionError):
        raise ConfigError(f"{field}: {index} is not a readable JSON object") from None
    if (
        not isinstance(wmap, dict)
        or not wmap
        or not all(isinstance(v, str) and Path(v).name == v for v in wmap.values())
    ):
        raise ConfigError(f"{field}: {index} has no valid weight_map (tensor name -> shard file in {p})")
    shapes: Shapes = {}
    for shard in sorted(set(wmap.values())):
        if not (p / shard).is_file():
            raise ConfigError(f"{field}: {index} names shard {shard!r}, which is missing")
        for name, shape in safetensors_header(p / shard, field).items():
            if wmap.get(name) == shard:
                shapes[name] = shape
    missing = [k for k in wmap if k not in shapes]
    if missing:
        raise ConfigError(
            f"{field}: {index} lists {len(missing)} tensor(s) that their shards lack, e.g. "
            f"{_short(missing[0])} in {wmap[missing[0]]!r}"
        )
    return shapes, f"the shards of {index}"


def match_shapes(got: Shapes, want: Shapes, what: str, field: str, optional: Iterable[str] = ()) -> None:
    """`got` must hold exactly the tensors of `want` (those in `optional` may be absent), each with its shape."""
    opt = set(optional)
    for name, shape in got.items():
        if name not in want:
            raise ConfigError(
                f"{field}: {what} holds tensor {_short(name)}, which config.json does not have "
                f"(weights of another model or config?)"
            )
        if tuple(shape) != want[name]:
            raise ConfigError(
                f"{field}: {what} does not match config.json: {name} has shape {list(shape)}, the "
                f"config needs {list(want[name])}"
            )
    missing = [k for k in want if k not in got and k not in opt]
    if missing:
        raise ConfigError(f"{field}: {what} lacks {len(missing)} tensor(s) that config.json needs, e.g. {missing[0]}")


# ---- the whole check -----------------------------------------------------------------------------------------
def validate_model_dir(
    path: str | Path, field: str = "model.path", max_gb: float | None = None, dtype: Any = None, extra_params: int = 0
) -> ModelCheck:
    """Everything about a Qwen3-VL directory that can be known without building a tensor (see the module doc).
    `extra_params`: parameters loaded on top of it (a LoRA adapter), counted in the budget."""
    p = check_model_dir(path, field)
    cfg_file = p / "config.json"
    cfg = qwen3vl_config(read_config(p, field), cfg_file, field)
    shapes = expected_tensors(cfg, cfg_file, field)
    params = count_params(shapes) + extra_params
    size, budget = params * element_bytes(dtype), model_budget(max_gb)
    if size > budget:  # before reading any weights: the config alone decides how much the model would take
        raise ConfigError(
            f"{field}: {cfg_file} describes {params:,} parameters, ~{human_bytes(size)} loaded, over "
            f"the {human_bytes(budget)} model memory budget (max_model_gb or ${BUDGET_ENV}; default: "
            f"half this machine's memory)"
        )
    got, what = weight_tensors(p, field)
    tied = ["lm_head.weight"] if getattr(cfg, "tie_word_embeddings", False) else []
    match_shapes(
        got,
        {**shapes, **({k: shapes["model.language_model.embed_tokens.weight"] for k in tied})},
        what,
        field,
        optional=tied,
    )  # a tied lm_head may be stored or not
    return ModelCheck(p, params, size, budget, shapes)


def load_processor(path: str | Path):
    from labrobfail_vlm.model.processor import LabRobFailProcessor

    p = check_model_dir(path, weights=False)
    try:
        return LabRobFailProcessor.from_pretrained(str(p))
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ConfigError(f"model: cannot load the processor from {path} ({type(e).__name__})") from None


def load_model(path: str | Path, dtype: Any = None, max_gb: float | None = None, **kwargs: Any):
    """Qwen3VLForConditionalGeneration from a validated directory (`max_gb`: the memory budget, see module doc)."""
    import torch
    from transformers import Qwen3VLForConditionalGeneration

    # load_model is public (train.py, merge.py, tests): it validates on its own, whoever called it
    p = validate_model_dir(path, "model.path", max_gb, dtype).path
    try:
        return Qwen3VLForConditionalGeneration.from_pretrained(
            str(p),
            dtype=dtype or torch.float32,
            use_safetensors=True,
            trust_remote_code=False,
            local_files_only=True,
            **kwargs,
        )
    except (OSError, ValueError, KeyError, RuntimeError) as e:
        raise ConfigError(
            f"model.path: cannot load {path} ({type(e).__name__}: {str(e).splitlines()[0][:200]})"
        ) from None
