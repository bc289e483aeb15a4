"""Merge a fine-tuned checkpoint (LoRA adapter + vision/merger weights) into a standalone Hugging Face model.

Run as:
    python scripts/merge.py src=outputs/demo_train/final out=outputs/demo_merged

The output loads with `Qwen3VLForConditionalGeneration.from_pretrained(OUT)` and carries the processor and
chat template, so infer.py and any transformers/vLLM stack can use it without peft.
"""

from __future__ import annotations

from pathlib import Path

from labrobfail_vlm.config import ConfigError, cli_main, load_config

DEFAULTS = """
src: null                  # a fine-tuned checkpoint (train.py's output_dir/final)
out: null                  # the standalone model folder to write (must not exist)
"""


def main(argv: list[str]) -> int:
    cfg = load_config(DEFAULTS, argv)
    if not isinstance(cfg.src, str) or not isinstance(cfg.out, str):
        raise ConfigError("src/out: give the checkpoint and the output folder (src=DIR out=DIR)")
    from labrobfail_vlm.model.loading import load_processor
    from labrobfail_vlm.train.checkpoint import is_finetuned, load_finetuned

    src, out = cfg.src, cfg.out
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
    cli_main(main, __doc__)
