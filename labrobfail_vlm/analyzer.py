"""FailureAnalyzer: the library API that reads a keyframe grid and answers the six questions.

    from labrobfail_vlm.analyzer import FailureAnalyzer
    fa = FailureAnalyzer.from_pretrained("outputs/demo_train/final")
    diagnosis = fa.analyze(grid_image, task="pick up the small beaker and place it on the target area")
    print(diagnosis.to_json())

Accepts a fine-tuned checkpoint (labrobfail.json: base + adapter + vision weights), a merged
model, or any local Qwen3-VL directory. Answers are decoded under constraints
(labrobfail_vlm.decoding), so a Diagnosis is always well-formed; after a "no failure"
answer, Q3-Q5 are not asked a failure-only option, and vice versa.
"""

from __future__ import annotations

import difflib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np
from PIL import Image

from labrobfail_vlm import questions as Q
from labrobfail_vlm.actions import to_primitives
from labrobfail_vlm.corrections import STRATEGIES, candidates
from labrobfail_vlm.grid import GridConfig, build_grid, sample_keyframes
from labrobfail_vlm.model.processor import common_prefix_len, expand_image_tokens
from labrobfail_vlm.taxonomy import Category, Severity


@dataclass
class Diagnosis:
    task: str
    actions: list[str]
    failure: bool
    failure_frame: int | None
    severity: int | None
    severity_name: str | None
    category: int | None
    category_name: str | None
    correction: str
    correction_strategy: str | None  # nearest entry of the paper's correction-strategy table
    primitives: list[dict[str, Any]] | None = None  # the correction through the action dictionary (actions.py)
    raw: dict[str, str] = field(default_factory=dict)  # the six decoded answers

    def to_json(self) -> str:
        return json.dumps(asdict(self), ensure_ascii=False)


def nearest_strategy(text: str) -> str | None:
    if not text or text == Q.NO_CORRECTION:
        return None
    scores = {k: difflib.SequenceMatcher(None, text.lower(), t.lower()).ratio() for k, (_, t) in STRATEGIES.items()}
    return max(scores, key=scores.__getitem__)


def frames_to_grid(frames: Sequence[Sequence[Image.Image | np.ndarray]], cfg: GridConfig = GridConfig(),
                   visible: int | None = None) -> Image.Image:
    """Per-view keyframe lists -> grid; more keyframes than the grid holds are thinned evenly."""
    n = len(frames[0])
    picks = sample_keyframes(list(range(n)), cfg.max_frames) if n > cfg.max_frames else list(range(n))
    return build_grid([[v[i] for i in picks] for v in frames], cfg, visible=visible)


Q6_MODES = ("free", "template")


class FailureAnalyzer:
    """`q6_mode`: "free" (greedy text) or "template" (the most likely entry of the paper's correction-strategy
    table, placeholders filled from the `objects` given to `analyze`, so every correction maps to primitives)."""

    def __init__(self, model: Any, processor: Any, grid: GridConfig = GridConfig(), q6_mode: str = "free"):
        from labrobfail_vlm.decoding import Decoder

        if q6_mode not in Q6_MODES:
            raise ValueError(f"q6_mode: expected one of {', '.join(Q6_MODES)}, got {q6_mode!r}")
        self.q6_mode = q6_mode
        self.model, self.processor = model.eval(), processor
        self.processor.tokenizer.padding_side = "left"
        self.decoder = Decoder(self.model, processor)
        self.grid = grid  # the layout the model was trained on: --frames grids and the Q3 range follow it
        self.num_frames, self.time_axis = grid.max_frames, grid.time_axis

    @classmethod
    def from_pretrained(cls, path: str | Path, dtype: Any = None, device: str | None = None,
                        **kwargs: Any) -> "FailureAnalyzer":
        import torch

        from labrobfail_vlm.model.loading import load_model, load_processor
        from labrobfail_vlm.train.checkpoint import is_finetuned, load_finetuned, trained_grid

        model = load_finetuned(path, dtype) if is_finetuned(path) else load_model(path, dtype)
        dev = device or ("cuda" if torch.cuda.is_available() else "cpu")
        if "grid" not in kwargs and (grid := trained_grid(path)) is not None:
            kwargs["grid"] = grid
        return cls(model.to(dev), load_processor(path), **kwargs)

    # ---- prompts -----------------------------------------------------------------------------------------
    def _prompt(self, dim: str, task: str) -> str:
        from labrobfail_vlm.train.data import messages

        q = Q.question_text(dim, 0, task, self.time_axis)
        return self.processor.apply_chat_template(messages(q), tokenize=False, add_generation_prompt=True)

    def _answer(self, dim: str, pre: Any, failed: bool | None, frames: int, objects: Sequence[str] = ()) -> str:
        d = self.decoder
        if dim == "Q1":
            return d.actions(pre)
        if dim == "Q2":
            return d.choose(pre, ["Yes", "No"])
        if dim == "Q6":  # consistent with Q2: no correction after "no failure"; after a failure an instruction,
            # not the no-correction sentence nor a closed-set reply (Yes/No/None/a number)
            if failed is False:
                return Q.NO_CORRECTION
            if self.q6_mode == "template":
                return d.choose(pre, [text for _, text in candidates(objects)])
            closed = [Q.NO_CORRECTION, Q.NO_FAILURE, "Yes", "No", *map(str, range(10))]
            return d.free_text(pre, avoid=closed if failed else ())
        if failed is False:
            return Q.NO_FAILURE
        hi = {"Q3": frames, "Q4": len(Severity), "Q5": len(Category)}[dim]
        return d.choose(pre, [str(i) for i in range(1, hi + 1)])

    def _prefixes(self, image: Image.Image, prompts: dict[str, str], one_pass: bool) -> Iterator[tuple[str, Any]]:
        """(dimension, model state after its prompt), in order. One pass shares the image+preamble prefix."""
        if not one_pass:
            for dim, p in prompts.items():
                yield dim, self.decoder.prefill(dict(self.processor(text=[p], images=[image], return_tensors="pt")))
            return
        first = next(iter(prompts.values()))
        one = self.processor(text=[first], images=[image], return_tensors="pt")
        # Token ids of all six prompts without re-processing the image: expand its placeholder by hand.
        ids = [self.decoder.encode_ids(expand_image_tokens(self.processor, p, one["image_grid_thw"][0]))
               for p in prompts.values()]
        assert ids[0] == one["input_ids"][0].tolist(), "prompt tokenization differs from the processor's"
        lcp = common_prefix_len(ids)
        text_cols = ("input_ids", "attention_mask", "mm_token_type_ids")
        pre = self.decoder.prefill({k: (v[:, :lcp] if k in text_cols else v) for k, v in one.items()})
        for dim, seq in zip(prompts, ids):
            q_pre, _ = self.decoder.extend(pre, seq[lcp:])
            yield dim, q_pre
            self.decoder.rewind(q_pre, pre)  # after the caller has answered from it

    def answers(self, image: Image.Image, task: str, one_pass: bool = True, frames: int | None = None,
                objects: Sequence[str] = (), dims: Sequence[str] = Q.DIMENSIONS) -> dict[str, str]:
        """The replies to `dims` (Q2 is always asked: the others follow its verdict)."""
        frames = frames or self.num_frames
        prompts = {dim: self._prompt(dim, task) for dim in Q.DIMENSIONS if dim in dims or dim == "Q2"}
        out: dict[str, str] = {}
        failed: bool | None = None
        for dim, pre in self._prefixes(image, prompts, one_pass):
            out[dim] = self._answer(dim, pre, failed, frames, objects)
            if dim == "Q2":
                failed = out[dim] == "Yes"
        return out

    def analyze(self, grid_or_frames: Image.Image | np.ndarray | Sequence[Sequence[Any]], task: str = "",
                one_pass: bool = True, frames: int | None = None, objects: Sequence[str] = ()) -> Diagnosis:
        """`objects`: the scene's object and place names (used by q6_mode="template")."""
        if isinstance(grid_or_frames, (Image.Image, np.ndarray)):
            img = grid_or_frames if isinstance(grid_or_frames, Image.Image) else Image.fromarray(grid_or_frames)
        else:
            frames = frames or min(len(grid_or_frames[0]), self.num_frames)
            img = frames_to_grid(grid_or_frames, self.grid)
        task = task or "a laboratory manipulation task"
        a = self.answers(img.convert("RGB"), task, one_pass, frames, objects)
        failed = a["Q2"] == "Yes"
        sev = int(a["Q4"]) if failed and a["Q4"].isdigit() else None
        cat = int(a["Q5"]) if failed and a["Q5"].isdigit() else None
        return Diagnosis(
            task=task, actions=[s.strip() for s in a["Q1"].split(",") if s.strip()], failure=failed,
            failure_frame=int(a["Q3"]) if failed and a["Q3"].isdigit() else None,
            severity=sev, severity_name=Severity(sev).title if sev else None,
            category=cat, category_name=Category(cat).title if cat else None,
            correction=a["Q6"], correction_strategy=nearest_strategy(a["Q6"]) if failed else None,
            primitives=to_primitives(a["Q6"], objects) if failed else [], raw=a)
