"""The tiny preset: a randomly initialised Qwen3-VL and a tokenizer trained on the project's own QA text.

It is written with `save_pretrained` into a directory and then loaded through exactly the
same path as a real checkpoint (labrobfail_vlm.model.loading), so CPU tests and `make demo`
exercise the real Qwen3-VL classes. Special tokens and the chat template follow Qwen's.

Run as:
    python -m labrobfail_vlm.model.tiny outputs/tiny_qwen3vl [DATASET_DIR]
"""

from __future__ import annotations

import json
import os
import shutil
import sys
from pathlib import Path
from typing import Any, Iterable

from tokenizers import Tokenizer, decoders, models, pre_tokenizers, trainers

from labrobfail_vlm.config import ConfigError

SPECIAL = [
    "<|endoftext|>",
    "<|im_start|>",
    "<|im_end|>",
    "<|vision_start|>",
    "<|vision_end|>",
    "<|image_pad|>",
    "<|video_pad|>",
]

# Qwen-style chat template. Whitespace control would eat the newline after the role, so it is emitted explicitly.
CHAT_TEMPLATE = (
    "{%- for message in messages -%}"
    "{{ '<|im_start|>' + message['role'] + '\\n' }}"
    "{%- if message['content'] is string -%}{{ message['content'] }}"
    "{%- else -%}{%- for c in message['content'] -%}"
    "{%- if c['type'] == 'image' -%}{{ '<|vision_start|><|image_pad|><|vision_end|>' }}"
    "{%- elif c['type'] == 'text' -%}{{ c['text'] }}{%- endif -%}"
    "{%- endfor -%}{%- endif -%}"
    "{{ '<|im_end|>\\n' }}"
    "{%- endfor -%}"
    "{%- if add_generation_prompt -%}{{ '<|im_start|>assistant\\n' }}{%- endif -%}"
)

TINY_VISION = {
    "depth": 2,
    "hidden_size": 64,
    "intermediate_size": 128,
    "num_heads": 4,
    "patch_size": 16,
    "spatial_merge_size": 2,
    "temporal_patch_size": 2,
    "num_position_embeddings": 2304,
    "deepstack_visual_indexes": [1],
}
TINY_TEXT = {
    "hidden_size": 128,
    "intermediate_size": 256,
    "num_hidden_layers": 2,
    "num_attention_heads": 4,
    "num_key_value_heads": 2,
    "head_dim": 32,
    "max_position_embeddings": 4096,
    "rope_parameters": {
        "rope_type": "default",
        "rope_theta": 5000000.0,
        "mrope_section": [6, 5, 5],
        "mrope_interleaved": True,
    },
}


def corpus(texts: Iterable[str] = ()) -> list[str]:
    """Every string the model must read or write: the questions, options, answers and corrections of
    labrobfail_vlm.questions/corrections, plus `texts` (a dataset's own records: task descriptions and object
    names come from there, so the model core never reads a simulator's scene module)."""
    from labrobfail_vlm import corrections, questions
    from labrobfail_vlm.taxonomy import ATOMIC_ACTIONS, FAILURE_TYPES

    base = [
        questions.PREAMBLE,
        questions.PREAMBLE_TIME_ROWS,
        questions.NO_CORRECTION,
        questions.NO_FAILURE,
        *questions.OPTIONS.values(),
        *(v.text for vs in questions.VARIANTS.values() for v in vs),
        *(t for _, t in corrections.STRATEGIES.values()),
        *(f.description for f in FAILURE_TYPES.values()),
        ", ".join(ATOMIC_ACTIONS),
        "Yes No",
        " ".join(str(i) for i in range(0, 64)),
    ]
    return base * 4 + list(texts)


def dataset_texts(dataset_dir: str | Path, split: str = "train") -> list[str]:
    """The human and gpt turns of one split of a dataset built by labrobfail-build-dataset (the training split by
    default: test-only words, such as unseen objects' names, stay out of the vocabulary, as they would for a
    real checkpoint's tokenizer; byte-level BPE still encodes them)."""
    recs = json.loads((Path(dataset_dir) / f"{split}.json").read_text())
    return [str(t["value"]) for r in recs for t in r["conversations"]]


def train_tokenizer(texts: Iterable[str] = (), vocab_size: int = 1024):
    from transformers import PreTrainedTokenizerFast

    tok = Tokenizer(models.BPE(unk_token=None))
    tok.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    tok.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(
        vocab_size=vocab_size,
        special_tokens=SPECIAL,
        show_progress=False,
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
    )
    tok.train_from_iterator(corpus(texts), trainer)
    fast = PreTrainedTokenizerFast(
        tokenizer_object=tok, eos_token="<|im_end|>", pad_token="<|endoftext|>", additional_special_tokens=SPECIAL[1:]
    )
    fast.chat_template = CHAT_TEMPLATE
    return fast


def check_built(
    path: str | Path, text: dict[str, Any], asked_by: str = "tiny_arch.text", fix: str = "delete it to build anew"
) -> None:
    """A tiny model already at `path` (a re-run or a resumed one reuses it) must have the decoder `text` asks for:
    otherwise a recipe that changed its size (make reproduce's REPRO_LAYERS) would train the old one unseen. Also
    `make reproduce-rows` / `make ablate`: rows beside a main model of another size would not compare."""
    built = json.loads((Path(path) / "config.json").read_text()).get("text_config", {})
    wrong = {k: (built.get(k), v) for k, v in text.items() if k in built and built[k] != v}
    if wrong:
        said = ", ".join(f"{k} {a} ({asked_by} asks {b})" for k, (a, b) in sorted(wrong.items()))
        raise ConfigError(f"model.path: {path} was built with another decoder: {said}; {fix}")


def build_tiny(
    out_dir: str | Path,
    seed: int = 0,
    texts: Iterable[str] = (),
    vision: dict[str, Any] | None = None,
    text: dict[str, Any] | None = None,
    tower: Path | None = None,
    replace: bool = False,
) -> Path:
    """Write a tiny random Qwen3-VL checkpoint (weights as safetensors, tokenizer, processor, template).

    `texts`: extra tokenizer corpus (a dataset's records); `vision`/`text`: overrides of TINY_VISION/TINY_TEXT;
    `tower`: a folder with a pretrained vision tower (labrobfail_vlm/model/tower.py), whose config replaces
    `vision` and whose weights replace the random tower's. `replace`: a folder already at `out_dir` is replaced
    whole; without it that folder is kept (another process, e.g. a DeepSpeed rank, built it from the same settings).
    """
    import torch
    from transformers import GenerationConfig, Qwen3VLConfig, Qwen3VLForConditionalGeneration

    from labrobfail_vlm.model import tower as T
    from labrobfail_vlm.model.processor import LabRobFailProcessor, image_processor

    out = Path(out_dir)
    card = T.read_card(tower) if tower is not None else None
    tok = train_tokenizer(texts)
    vis = {**TINY_VISION, **(T.vision_overrides(card) if card else (vision or {}))}
    txt = {**TINY_TEXT, **(text or {})}
    if card and int(card["out_hidden_size"]) != int(txt["hidden_size"]):
        raise ConfigError(
            f"tower: {tower} feeds {card['out_hidden_size']}-wide tokens, the decoder is "
            f"{txt['hidden_size']} wide (tiny_arch.text.hidden_size)"
        )
    ids = {t: tok.convert_tokens_to_ids(t) for t in SPECIAL}
    cfg = Qwen3VLConfig(
        text_config={**txt, "vocab_size": len(tok), "pad_token_id": ids["<|endoftext|>"]},
        vision_config={**vis, "out_hidden_size": txt["hidden_size"]},
        image_token_id=ids["<|image_pad|>"],
        video_token_id=ids["<|video_pad|>"],
        vision_start_token_id=ids["<|vision_start|>"],
        vision_end_token_id=ids["<|vision_end|>"],
    )
    torch.manual_seed(seed)
    model = Qwen3VLForConditionalGeneration(cfg)
    if tower is not None:
        T.load_visual(model.model.visual, tower)
    # A config-built model has no eos in its generation config: without it generate never stops.
    model.generation_config = GenerationConfig(
        eos_token_id=ids["<|im_end|>"], pad_token_id=ids["<|endoftext|>"], do_sample=False
    )
    # Written beside and renamed into place: a kill mid-write leaves no folder a later run takes as built, and the
    # ranks of a DeepSpeed run that each build it (same seed, same model) never read another's half-written files.
    tmp = out.with_name(f"{out.name}.{os.getpid()}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    model.save_pretrained(tmp, safe_serialization=True)
    ip = image_processor(temporal_patch_size=vis["temporal_patch_size"])
    LabRobFailProcessor(image_processor=ip, tokenizer=tok, chat_template=CHAT_TEMPLATE).save_pretrained(tmp)
    if replace and out.is_dir():
        from labrobfail_vlm.io import swap_in

        swap_in(tmp, out)
        return out
    try:
        tmp.rename(out)
    except OSError:  # built by another rank first
        shutil.rmtree(tmp, ignore_errors=True)
        if not out.is_dir():
            raise
    return out


if __name__ == "__main__":
    print(
        build_tiny(
            sys.argv[1] if len(sys.argv) > 1 else "outputs/tiny_qwen3vl",
            texts=dataset_texts(sys.argv[2]) if len(sys.argv) > 2 else (),
            replace=True,
        )
    )
