"""VQA records -> Qwen3-VL training batches, with the loss on the answer tokens only.

Labels are masked through the chat template: the prompt (user turn + generation prompt)
is rendered by the processor's own template and everything up to its length is ignored,
so no token ids are hard-coded and a real checkpoint's template works unchanged.
Exactly one image per sample; a sample whose tokens would be cut inside the image (or at
all) is an error, never a silent truncation.
"""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path
from typing import Any, Callable, Sequence

import torch
from PIL import Image
from torch.utils.data import Dataset

from labrobfail_vlm import questions as Q
from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.model.processor import common_prefix_len
from labrobfail_vlm.train.tower_cache import file_key

IGNORE = -100


class GridAugment:
    """Augments keyframe grids of one layout (labrobfail_vlm/augment.py). A pair's draw is seeded by the run's seed,
    the pass (`epoch`: stage A's and the VQA stage's apart) and the pair, not taken from a running generator: a resumed
    run skips the batches it trained and accelerate's loader collates one batch ahead, so a generator's state at a
    checkpoint would not be the one the next batch needs, and the same seed would give other data after a resume.
    A pair drawn twice in one pass (extra_repeat) gets the same draw both times."""

    def __init__(self, cfg: Any, grid: Any, views: int, seed: int = 0):
        self.cfg, self.grid, self.views, self.seed = cfg, grid, int(views), int(seed)
        self.epoch: tuple[int, int] = (1, 0)  # (0: stage A, 1: the VQA stage; its epoch), set as each pass begins

    def draw(self, group: str) -> Any:
        import zlib

        import numpy as np

        from labrobfail_vlm.augment import Augment

        rng = np.random.default_rng([self.seed, 0xA06, *self.epoch, zlib.crc32(group.encode())])
        return Augment.draw(self.cfg, self.views, rng)

    def __call__(self, img: Image.Image, aug: Any) -> Image.Image:
        from labrobfail_vlm.augment import augment_grid

        return augment_grid(img, self.grid, self.views, aug)


def messages(question: str, answer: str | None = None) -> list[dict[str, Any]]:
    """Chat messages for one record; the record's leading "<image>\\n" becomes the image slot."""
    text = question.removeprefix("<image>\n")
    msgs: list[dict[str, Any]] = [{"role": "user", "content": [{"type": "image"}, {"type": "text", "text": text}]}]
    if answer is not None:
        msgs.append({"role": "assistant", "content": [{"type": "text", "text": answer}]})
    return msgs


class VQADataset(Dataset):
    """One split of a dataset built by labrobfail-build-dataset."""

    def __init__(self, dataset_dir: str | Path, split: str = "train", extra: Sequence[str | Path] = ()):
        """`extra`: more datasets whose same split is added (train.py's extra_train), each record's image read
        from its own dataset (a record id or trajectory found twice is an error: two datasets built alike)."""
        self.root = Path(dataset_dir)
        self.records, self.group_of = [], {}
        for root in (self.root, *map(Path, extra)):
            records, groups = self._read(root, split)
            if root != self.root:  # an absolute image path: self.root / it is it
                records = [{**r, "image": str((root / r["image"]).resolve())} for r in records]
            twice = {r["id"] for r in records} & {r["id"] for r in self.records} or groups.keys() & self.group_of.keys()
            if twice:
                raise ConfigError(f"extra_train: {root} repeats {sorted(twice)[0]!r} of an earlier dataset")
            self.records += records
            self.group_of |= groups
            if root == self.root:
                self.extra_from = len(self.records)  # records from here on come from `extra`

    @staticmethod
    def _read(root: Path, split: str) -> tuple[list[dict[str, Any]], dict[str, str]]:
        path = root / f"{split}.json"
        if not path.is_file():
            raise ConfigError(f"dataset_dir: {path} not found (build it with labrobfail-build-dataset)")
        try:
            records = json.loads(path.read_text())
        except ValueError as e:
            raise ConfigError(f"dataset_dir: {path} is not valid JSON ({e})") from None
        for r in records[:1]:
            if not {"id", "image", "conversations"} <= set(r):
                raise ConfigError(f"dataset_dir: {path} records lack id/image/conversations")
        # trajectory -> its success/failure pair (the curriculum's pair batches); absent in older datasets
        meta = root / "trajectories.json"
        trajs = json.loads(meta.read_text()) if meta.is_file() else []
        groups = {t["trajectory"]: t["group"] for t in trajs if "group" in t}
        return records, groups

    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, i: int) -> dict[str, Any]:
        r = self.records[i]
        human, gpt = r["conversations"]
        if human["value"].count("<image>") != 1:
            raise ValueError(f"record {r['id']}: exactly one <image> per sample is supported")
        return {"id": r["id"], "image": str(self.root / r["image"]), "question": human["value"], "answer": gpt["value"]}


def pack_rows(rows: list[dict[str, Any]], pad_id: int) -> dict[str, torch.Tensor]:
    """Right-pad packed rows ({ids, labels, types, seg, shift, slots}) into batch tensors.

    `seg`: 0 for the prefix, k >= 1 for branch k, -1 for padding; `shift`: what to subtract from a token's
    plain sequential position so that its branch restarts where the prefix ends; `slot`: the record index of
    each label token (for the per-record loss), -1 elsewhere.
    """
    n = max(len(r["ids"]) for r in rows)

    def pad(key: str, value: int) -> torch.Tensor:
        return torch.tensor([r[key] + [value] * (n - len(r[key])) for r in rows])

    return {
        "input_ids": pad("ids", pad_id),
        "labels": pad("labels", IGNORE),
        "mm_token_type_ids": pad("types", 0),
        "attention_mask": pad("mask", 0),
        "segment_ids": pad("seg", -1),
        "position_shift": pad("shift", 0),
        "label_slot": pad("slots", -1),
    }


def answer_balance(records: Any, exponents: dict[str, float]) -> dict[str, dict[str, float]]:
    """Per question named in `exponents`, a weight per answer that evens out its answer frequencies in `records`
    (a VQADataset, or any sequence of its items: the same `answer` the Collator weighs): count ** -p, scaled so
    that the question's records keep a mean weight of 1. p = 0 changes nothing; p = 1 gives every answer the same
    total weight. For a closed-set question whose majority answer a small model learns to give whatever it sees
    (Q4, severity: most failures are Dangerous)."""
    bad = {k: v for k, v in exponents.items() if k not in Q.DIMENSIONS or not 0.0 <= float(v) <= 1.0}
    if bad:
        raise ConfigError(
            f"loss.balance: expected an exponent in [0, 1] for any of {', '.join(Q.DIMENSIONS)}; got {bad}"
        )
    out: dict[str, dict[str, float]] = {}
    for dim, p in exponents.items():
        if float(p) == 0.0:
            continue
        items = (records[i] for i in range(len(records)))
        counts = Counter(r["answer"] for r in items if Q.dim_of(r["id"]) == dim)
        if not counts:
            raise ConfigError(f"loss.balance: the training split has no {dim} records")
        raw = {a: c ** -float(p) for a, c in counts.items()}
        mean = sum(raw[a] * c for a, c in counts.items()) / sum(counts.values())
        out[dim] = {a: w / mean for a, w in raw.items()}
    return out


class Collator:
    """Batches for `model(**batch)`. With `question_weights` (dimension -> weight, default 1) each batch also
    carries `record_weight`, which the trainer's record loss pops before the forward pass; `answer_weights`
    (answer_balance's) multiplies a record's weight by its answer's."""

    def __init__(
        self,
        processor: Any,
        max_length: int = 2048,
        question_weights: dict[str, float] | None = None,
        rewording: Callable[[list[dict[str, Any]]], list[dict[str, Any]]] | None = None,
        frame_targets: dict[str, list[float]] | None = None,
        group_of: dict[str, str] | None = None,
        augment: "GridAugment | None" = None,
        tower_cache: Any = None,
        answer_weights: dict[str, dict[str, float]] | None = None,
    ):
        self.processor = processor
        self.augment = augment  # twin-consistent image augmentation (training only)
        # a frozen tower's TowerCache: packed batches then name each grid by its file, and a grid it has stored is
        # not read or preprocessed again (labrobfail_vlm/train/tower_cache.py); never with augmentation
        self.tower_cache = tower_cache if augment is None else None
        self._pixels: dict[str, tuple[torch.Tensor, int, torch.dtype]] = {}  # path -> grid_thw, row width, dtype
        # grounding (labrobfail_vlm/train/grounding.py): per-frame targets and twin ids, one row per image
        self.frame_targets, self.group_of = frame_targets, group_of or {}
        self.rewording = rewording  # labrobfail_vlm.train.curriculum.Rewording
        self.max_length = int(max_length)
        self.image_token = processor.image_token
        self.weights: dict[str, float] | None = None
        self.answer_weights = answer_weights or {}
        if self.answer_weights and question_weights is None:
            raise ConfigError("loss.balance: needs loss.mode=record (the token mean weighs no record)")
        if question_weights is not None:  # "aux": each auxiliary fact record (labrobfail_data/facts.py)
            self.weights = {d: 1.0 for d in (*Q.DIMENSIONS, "aux")} | {
                str(k): float(v) for k, v in question_weights.items()
            }
            if set(self.weights) - {*Q.DIMENSIONS, "aux"} or any(w < 0 for w in self.weights.values()):
                raise ConfigError(
                    f"loss.question_weights: expected non-negative weights for "
                    f"{', '.join(Q.DIMENSIONS)}, aux; got {dict(question_weights)}"
                )

    def weight(self, rec: dict[str, Any]) -> float:
        """The record's loss weight: its question's, times the curriculum's `weight_scale` (detect_first)."""
        scale = float(rec.get("weight_scale", 1.0))
        if self.weights is None:
            return scale
        dim = Q.dim_of(rec["id"])
        balance = self.answer_weights.get(dim, {}).get(rec["answer"], 1.0)
        return self.weights["aux" if Q.is_aux(dim) else dim] * scale * balance

    def add_grounding(self, batch: dict[str, Any], record_ids: list[str]) -> None:
        """`frame_target` (rows, max_frames) and `pair_group` (rows,) for the images of a batch, one per row."""
        if self.frame_targets is None:
            return
        trajs = [Q.traj_of(r) for r in record_ids]
        missing = [t for t in trajs if t not in self.frame_targets]
        if missing:
            raise ValueError(f"grounding: trajectory {missing[0]} has no frame targets in trajectories.json")
        groups = {g: i for i, g in enumerate(dict.fromkeys(self.group_of.get(t, t) for t in trajs))}
        batch["frame_target"] = torch.tensor([self.frame_targets[t] for t in trajs])
        batch["pair_group"] = torch.tensor([groups[self.group_of.get(t, t)] for t in trajs])

    def images(self, recs: list[dict[str, Any]]) -> list[Image.Image]:
        """Each record's grid, augmented when `augment` is set: one draw per success/failure pair in the batch,
        so both twins change alike and still differ by the failure alone."""
        imgs = [Image.open(r["image"]).convert("RGB") for r in recs]
        if self.augment is None:
            return imgs
        groups = [self.group_of.get(Q.traj_of(r["id"]), Q.traj_of(r["id"])) for r in recs]
        draws = {g: self.augment.draw(g) for g in dict.fromkeys(groups)}
        return [self.augment(img, draws[g]) for img, g in zip(imgs, groups)]

    def _ids(self, texts: list[str], grid_thw: torch.Tensor) -> list[list[int]]:
        """Token ids of texts holding one image placeholder, as the processor would make them: the
        placeholder is a special token, so it is tokenized alone and repeated once per visual token after
        (tokenizing the expanded string is ~5x slower and gives the same ids)."""
        tok = self.processor.tokenizer
        pad = tok.convert_tokens_to_ids(self.image_token)
        n = int(grid_thw.prod()) // self.processor.image_processor.merge_size**2
        out = []
        for ids in tok(texts, add_special_tokens=False)["input_ids"]:
            i = ids.index(pad)
            out.append(ids[:i] + [pad] * n + ids[i + 1 :])
        return out

    def packed(self, items: list[list[dict[str, Any]]]) -> dict[str, torch.Tensor]:
        """Items of labrobfail_vlm.train.packing.TrajectoryDataset -> one packed row per trajectory."""
        proc = self.processor
        flat = [r for recs in items for r in recs]
        if self.rewording is not None:  # over the whole batch, so twins in different rows share a wording
            flat = self.rewording(flat)
        rows, pixels, thws, weights = [], [], [], []
        image_id = proc.tokenizer.convert_tokens_to_ids(self.image_token)
        at = 0
        cache = self.tower_cache
        keys = [file_key(recs[0]["image"]) for recs in items] if cache is not None else None
        # a grid is served by its key once the tower stored it and its grid size was read from it
        stored = (
            [k in cache and r[0]["image"] in self._pixels for k, r in zip(keys, items)]
            if keys
            else [False] * len(items)
        )
        grids = iter(self.images([recs[0] for recs, s in zip(items, stored) if not s]))
        for recs, known in zip(items, stored):
            path = recs[0]["image"]
            recs, at = flat[at : at + len(recs)], at + len(recs)
            fulls = [proc.apply_chat_template(messages(b["question"], b["answer"]), tokenize=False) for b in recs]
            prompts = [
                proc.apply_chat_template(messages(b["question"]), tokenize=False, add_generation_prompt=True)
                for b in recs
            ]
            enc = None
            if known:  # the tower serves this grid from its file key: its pixels are never read
                thw, width, dtype = self._pixels[path]
                px = torch.zeros(1, width, dtype=dtype).expand(int(thw.prod()), width)
            else:
                enc = proc(text=fulls[:1], images=[next(grids)], return_tensors="pt")
                thw, px = enc["image_grid_thw"][0], enc["pixel_values"]
                self._pixels[path] = (thw, int(px.shape[1]), px.dtype)
            ids = self._ids(fulls + prompts, thw)
            f_ids, p_ids = ids[: len(fulls)], ids[len(fulls) :]
            if enc is not None and f_ids[0] != enc["input_ids"][0].tolist():
                raise ValueError(f"sample {recs[0]['id']}: tokenization differs from the processor's")
            # the shared prefix stops before every prompt's end, so each branch keeps a question token
            k = min(common_prefix_len(f_ids), min(len(p) for p in p_ids) - 1)
            row: dict[str, list[int]] = {
                "ids": f_ids[0][:k],
                "labels": [IGNORE] * k,
                "seg": [0] * k,
                "shift": [0] * k,
                "slots": [-1] * k,
            }
            for j, (b, f, p) in enumerate(zip(recs, f_ids, p_ids), 1):
                pl = len(p)
                if pl <= k or f[:pl] != p:
                    raise ValueError(f"sample {b['id']}: its prompt is not a proper prefix of the packed branch")
                branch, start, slot = f[k:], len(row["ids"]), len(weights)
                row["ids"] += branch
                row["seg"] += [j] * len(branch)
                row["shift"] += [start - k] * len(branch)
                row["labels"] += [IGNORE] * (pl - k) + branch[pl - k :]
                row["slots"] += [-1] * (pl - k) + [slot] * (len(f) - pl)
                weights.append(self.weight(b))
            if len(row["ids"]) > self.max_length:
                raise ValueError(
                    f"sample {recs[0]['id']}: {len(row['ids'])} packed tokens exceed max_length="
                    f"{self.max_length}; raise max_length or shrink the grid"
                )
            row["types"] = [int(t == image_id) for t in row["ids"]]
            row["mask"] = [1] * len(row["ids"])
            rows.append(row)
            pixels.append(px)
            thws.append(thw)
        batch = pack_rows(rows, int(proc.tokenizer.pad_token_id))
        batch.update(
            pixel_values=torch.cat(pixels), image_grid_thw=torch.stack(thws), record_weight=torch.tensor(weights)
        )
        if keys is not None:
            batch["grid_keys"] = keys  # popped by HybridTrainer.compute_loss and handed to the tower cache
        self.add_grounding(batch, [recs[0]["id"] for recs in items])
        return batch

    def __call__(self, batch: list[Any]) -> dict[str, torch.Tensor]:
        if batch and isinstance(batch[0], list):  # trajectories: shared-prefix packing
            return self.packed(batch)
        proc, tok = self.processor, self.processor.tokenizer
        if self.rewording is not None:
            batch = self.rewording(batch)
        images = self.images(batch)
        fulls = [proc.apply_chat_template(messages(b["question"], b["answer"]), tokenize=False) for b in batch]
        prompts = [
            proc.apply_chat_template(messages(b["question"]), tokenize=False, add_generation_prompt=True) for b in batch
        ]
        enc = proc(text=fulls, images=images, padding=True, return_tensors="pt")
        labels = enc["input_ids"].clone()
        labels[enc["attention_mask"] == 0] = IGNORE
        for i, (b, prompt) in enumerate(zip(batch, prompts)):
            p_ids = self._ids([prompt], enc["image_grid_thw"][i])[0]
            n_img = int((enc["input_ids"][i] == tok.convert_tokens_to_ids(self.image_token)).sum())
            length = int(enc["attention_mask"][i].sum())
            if length > self.max_length:
                raise ValueError(
                    f"sample {b['id']}: {length} tokens exceed max_length={self.max_length} "
                    f"({n_img} of them visual); raise max_length or shrink the grid"
                )
            if enc["input_ids"][i, : len(p_ids)].tolist() != p_ids:
                raise ValueError(
                    f"sample {b['id']}: the chat template's prompt is not a prefix of the full "
                    "conversation; cannot mask labels"
                )
            labels[i, : len(p_ids)] = IGNORE
        enc["labels"] = labels
        if self.weights is not None:
            enc["record_weight"] = torch.tensor([self.weight(b) for b in batch])
        out = dict(enc)
        self.add_grounding(out, [b["id"] for b in batch])
        return out
