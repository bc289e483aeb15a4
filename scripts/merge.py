"""Merge a fine-tuned checkpoint (LoRA adapter + vision/merger weights) into a standalone Hugging Face model.

Run as:
    python scripts/merge.py outputs/demo_train/final outputs/demo_merged

The output loads with `Qwen3VLForConditionalGeneration.from_pretrained(OUT)` and carries the processor and
chat template, so infer.py and any transformers/vLLM stack can use it without peft.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from labrobfail_vlm.config import ConfigError, cli_main  # noqa: E402


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        raise ConfigError("usage: python scripts/merge.py CHECKPOINT_DIR OUT_DIR")
    from labrobfail_vlm.model.loading import load_processor
    from labrobfail_vlm.train.checkpoint import is_finetuned, load_finetuned

    src, out = argv
    if not is_finetuned(src):
        raise ConfigError(f"checkpoint: {src} is not a LabRobFail fine-tuned checkpoint (no labrobfail.json)")
    model = load_finetuned(src)
    if hasattr(model, "merge_and_unload"):
        model = model.merge_and_unload()
    tmp = Path(out + ".tmp")
    model.save_pretrained(tmp, safe_serialization=True)
    load_processor(src).save_pretrained(tmp)
    if Path(out).exists():
        raise ConfigError(f"out: {out} already exists; nothing was overwritten (merged model left in {tmp})")
    tmp.rename(out)
    print(out)
    return 0


if __name__ == "__main__":
    cli_main(main)
