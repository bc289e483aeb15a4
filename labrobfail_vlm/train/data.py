"""VQA records -> Qwen3-VL training batches, with the loss on the answer tokens only.

Labels are masked through the chat template: the prompt (user turn + generation prompt)
is rendered by the processor's own template and everything up to its length is ignored,
so no token ids are hard-coded and a real checkpoint's template works unchanged.
Exactly one image per sample; a sample whose tokens would be cut inside the image (or at
all) is an error, never a silent truncation.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from PIL import Image
from torch.utils.data import Dataset

from labrobfail_vlm import questions as Q
from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.model.processor import expand_image_tokens

IGNORE = -100


def messages(question: str, answer: str | None = None) -> list[dict[str, Any]]:
    """Chat messages for one record; the record's leading "<image>\\n" becomes the image slot."""
    text = question.removeprefix("<image>\n")
    msgs: list[dict[str, Any]] = [{"role": "user", "content": [{"type": "image"}, {"type": "text", "text": text}]}]
    if answer is not None:
        msgs.append({"role": "assistant", "content": [{"type": "text", "text": answer}]})
    return msgs


class VQADataset(Dataset):
    """One split of a dataset built by scripts/build_dataset.py."""

    def __init__(self, dataset_dir: str | Path, split: str = "train"):
        self.root = Path(dataset_dir)
        path = self.root / f"{split}.json"
        if not path.is_file():
            raise ConfigError(f"dataset_dir: {path} not found (build it with scripts/build_dataset.py)")
        try:
            self.records = json.loads(path.read_text())
        except ValueError as e:
            raise ConfigError(f"dataset_dir: {path} is not valid JSON ({e})") from None
        for r in self.records[:1]:
            if not {"id", "image", "conversations"} <= set(r):
                raise ConfigError(f"dataset_dir: {path} records lack id/image/conversations")

    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, i: int) -> dict[str, Any]:
        r = self.records[i]
        human, gpt = r["conversations"]
        if human["value"].count("<image>") != 1:
            raise ValueError(f"record {r['id']}: exactly one <image> per sample is supported")
        return {"id": r["id"], "image": str(self.root / r["image"]), "question": human["value"],
                "answer": gpt["value"]}


class Collator:
    """Batches for `model(**batch)`. With `question_weights` (dimension -> weight, default 1) each batch also
    carries `record_weight`, which the trainer's record loss pops before the forward pass."""

    def __init__(self, processor: Any, max_length: int = 2048, question_weights: dict[str, float] | None = None):
        self.processor = processor
        self.max_length = int(max_length)
        self.image_token = processor.image_token
        self.weights: dict[str, float] | None = None
        if question_weights is not None:
            self.weights = {d: 1.0 for d in Q.DIMENSIONS} | {str(k): float(v) for k, v in question_weights.items()}
            if set(self.weights) - set(Q.DIMENSIONS) or any(w < 0 for w in self.weights.values()):
                raise ConfigError(f"loss.question_weights: expected non-negative weights for "
                                  f"{', '.join(Q.DIMENSIONS)}, got {dict(question_weights)}")

    def __call__(self, batch: list[dict[str, Any]]) -> dict[str, torch.Tensor]:
        proc, tok = self.processor, self.processor.tokenizer
        images = [Image.open(b["image"]).convert("RGB") for b in batch]
        fulls = [proc.apply_chat_template(messages(b["question"], b["answer"]), tokenize=False) for b in batch]
        prompts = [proc.apply_chat_template(messages(b["question"]), tokenize=False, add_generation_prompt=True)
                   for b in batch]
        enc = proc(text=fulls, images=images, padding=True, return_tensors="pt")
        labels = enc["input_ids"].clone()
        labels[enc["attention_mask"] == 0] = IGNORE
        for i, (b, prompt) in enumerate(zip(batch, prompts)):
            expanded = expand_image_tokens(proc, prompt, enc["image_grid_thw"][i])
            p_ids = tok(expanded, add_special_tokens=False)["input_ids"]
            n_img = expanded.count(self.image_token)
            length = int(enc["attention_mask"][i].sum())
            if length > self.max_length:
                raise ValueError(f"sample {b['id']}: {length} tokens exceed max_length={self.max_length} "
                                 f"({n_img} of them visual); raise max_length or shrink the grid")
            if enc["input_ids"][i, :len(p_ids)].tolist() != p_ids:
                raise ValueError(f"sample {b['id']}: the chat template's prompt is not a prefix of the full "
                                 "conversation; cannot mask labels")
            labels[i, :len(p_ids)] = IGNORE
        enc["labels"] = labels
        if self.weights is not None:
            enc["record_weight"] = torch.tensor([self.weights[Q.dim_of(b["id"])] for b in batch])
        return dict(enc)
