"""A Qwen3-VL processor with no video processor, sized so the keyframe grid keeps every visual token.

Stock `Qwen3VLProcessor(...)` cannot be built without torchvision (its video processor);
the project never feeds video, so the subclass passes `video_processor=None`.
The image path is the pure-PIL `Qwen2VLImageProcessorPil` (16 px patches, 2x2 merge: one
visual token per 32x32 px), with max_pixels = the grid's area so a 1536x768 grid keeps all
1152 tokens instead of the common default's ~49.
"""

from __future__ import annotations

from typing import Any

from transformers import Qwen3VLProcessor
from transformers.models.qwen2_vl.image_processing_pil_qwen2_vl import Qwen2VLImageProcessorPil

GRID_PIXELS = 1536 * 768
MIN_PIXELS = 32 * 32 * 4


class LabRobFailProcessor(Qwen3VLProcessor):
    """Qwen3VLProcessor minus video: exactly one image per sample."""

    # No `video_processor` in the signature: ProcessorMixin derives its sub-processors from it.
    def __init__(self, image_processor=None, tokenizer=None, chat_template=None, **kwargs: Any):
        super().__init__(image_processor, tokenizer, None, chat_template=chat_template, **kwargs)

    @classmethod
    def from_pretrained(cls, path: str, **kwargs: Any) -> "LabRobFailProcessor":  # type: ignore[override]
        from transformers import AutoTokenizer

        tok = AutoTokenizer.from_pretrained(path, trust_remote_code=False)
        ip = Qwen2VLImageProcessorPil.from_pretrained(path, **kwargs)
        return cls(image_processor=ip, tokenizer=tok, chat_template=tok.chat_template)


def image_processor(
    max_pixels: int = GRID_PIXELS, min_pixels: int = MIN_PIXELS, temporal_patch_size: int = 2
) -> Qwen2VLImageProcessorPil:
    """`temporal_patch_size` must match the vision tower's (Qwen3-VL: 2, an image is fed as two equal frames)."""
    return Qwen2VLImageProcessorPil(
        patch_size=16,
        temporal_patch_size=temporal_patch_size,
        merge_size=2,
        size={"shortest_edge": min_pixels, "longest_edge": max_pixels},
    )


def common_prefix_len(seqs: list[list[int]]) -> int:
    """Length of the longest common prefix of token sequences (the image and preamble that prompts share)."""
    n = min(len(s) for s in seqs)
    return next((i for i in range(n) if len({s[i] for s in seqs}) > 1), n)


def visual_tokens(width: int, height: int) -> int:
    """Visual tokens of an image that needs no resizing (both sides multiples of 32)."""
    return (width // 32) * (height // 32)
