"""FailureAnalyzer: the library API that reads a keyframe grid and answers the six questions.

    from labrobfail_vlm.analyzer import FailureAnalyzer
    fa = FailureAnalyzer.from_pretrained("outputs/demo_train/final")
    diagnosis = fa.analyze(grid_image, task="pick up the small beaker and place it on the target area")
    print(diagnosis.to_json())
    diagnoses = fa.analyze_batch([grid_a, grid_b, DiagnosisRequest(frames, task="...")])  # same answers, batched

Accepts a fine-tuned checkpoint (labrobfail.json: base + adapter + vision weights), a merged
model, or any local Qwen3-VL directory. Answers are decoded under constraints
(labrobfail_vlm.decoding), so a Diagnosis is always well-formed; after a "no failure"
answer, Q3-Q5 are not asked a failure-only option, and vice versa. Q2 also comes as a score:
`Diagnosis.p_failure`, the constrained decoder's probability of "Yes" (a failure) against "No", or with
`failure_score` "questions" (or "wordings": in every taught wording) the mean of that and each closed failure-only
question's probability of not "None".
"""

from __future__ import annotations

import difflib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Collection, Iterator, Mapping, Sequence

import numpy as np
from PIL import Image

from labrobfail_vlm import questions as Q
from labrobfail_vlm.actions import to_primitives
from labrobfail_vlm.corrections import STRATEGIES, candidates
from labrobfail_vlm.failure_score import (
    Q2_OPTIONS,
    check_failure_score,
    read_rows,
    score_reads,
    shared_rows,
    verdicts,
)
from labrobfail_vlm.grid import GridConfig, build_grid, fit_grid, sample_keyframes
from labrobfail_vlm.model.processor import common_prefix_len
from labrobfail_vlm.option_bias import BIASED_DIMS, biased_choice, check_option_bias, numbered_options
from labrobfail_vlm.taxonomy import Category, Severity


@dataclass
class Diagnosis:
    task: str
    actions: list[str]
    failure: bool
    failure_frame: int | None
    severity: int | None
    severity_name: str | None  # the paper's answer option (appendix), e.g. "Dangerous Level"
    category: int | None
    category_name: str | None
    correction: str
    correction_strategy: str | None  # nearest entry of the paper's correction-strategy table
    primitives: list[dict[str, Any]] | None = None  # the correction through the action dictionary (actions.py)
    raw: dict[str, str] = field(default_factory=dict)  # the six decoded answers
    # the same level as the paper's main text names it (taxonomy.SEVERITY_MAIN_TEXT: paired by position)
    severity_main_text: str | None = None
    # P(failure): softmax over the log-likelihoods of the two admissible Q2 replies (failure_score "q2"), or the
    # mean of that and 1 - P("None") on Q3, Q4 and Q5 ("questions"; "wordings": in each wording of each); `failure`
    # is p_failure >= the operating point. None where the answers came without scores (an endpoint, a replayed reply).
    p_failure: float | None = None

    def to_json(self) -> str:
        return json.dumps(asdict(self), ensure_ascii=False)


class Answers(dict[str, str]):
    """The decoded replies keyed by dimension, plus `p_failure` (P("Yes") for Q2) when the model scored it and
    `option_scores` (dimension -> the log-likelihood of each option, before any option bias) for the closed
    failure-only questions the model answered."""

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.p_failure: float | None = None
        self.option_scores: dict[str, list[float]] = {}


def nearest_strategy(text: str) -> str | None:
    if not text or text == Q.NO_CORRECTION:
        return None
    scores = {k: difflib.SequenceMatcher(None, text.lower(), t.lower()).ratio() for k, (_, t) in STRATEGIES.items()}
    return max(scores, key=scores.__getitem__)


def diagnosis_of(a: Mapping[str, str], task: str, objects: Sequence[str] = ()) -> Diagnosis:
    """The Diagnosis the six replies `a` (an Answers, or a plain mapping without P(failure)) make for `task`;
    `objects` name the scene's things for the correction's primitives."""
    failed = a["Q2"] == "Yes"
    sev = int(a["Q4"]) if failed and a["Q4"].isdigit() else None
    cat = int(a["Q5"]) if failed and a["Q5"].isdigit() else None
    return Diagnosis(
        task=task,
        actions=[s.strip() for s in a["Q1"].split(",") if s.strip()],
        failure=failed,
        failure_frame=int(a["Q3"]) if failed and a["Q3"].isdigit() else None,
        severity=sev,
        severity_name=Severity(sev).title if sev else None,
        category=cat,
        category_name=Category(cat).title if cat else None,
        correction=a["Q6"],
        correction_strategy=nearest_strategy(a["Q6"]) if failed else None,
        primitives=to_primitives(a["Q6"], objects) if failed else [],
        raw=dict(a),
        severity_main_text=Severity(sev).main_text if sev else None,
        p_failure=None if getattr(a, "p_failure", None) is None else round(float(a.p_failure), 6),  # type: ignore[attr-defined]
    )


def frames_to_grid(
    frames: Sequence[Sequence[Image.Image | np.ndarray]], cfg: GridConfig = GridConfig(), visible: int | None = None
) -> Image.Image:
    """Per-view keyframe lists -> grid; more keyframes than the grid holds are thinned evenly."""
    n = len(frames[0])
    picks = sample_keyframes(list(range(n)), cfg.max_frames) if n > cfg.max_frames else list(range(n))
    return build_grid([[v[i] for i in picks] for v in frames], cfg, visible=visible)


Q6_MODES = ("free", "template")


@dataclass(frozen=True)
class Ask:
    """What the model must decode for one reply: "choose" among `options`, "actions" (Q1), or "free" text that
    may not open like any of `options`."""

    kind: str
    options: tuple[str, ...] = ()
    per_token: bool = False  # "choose": rank options by mean log-likelihood per token (options of unequal length)


def plan_reply(
    dim: str,
    failed: bool | None,
    frames: int,
    objects: Sequence[str] = (),
    q6_mode: str = "free",
    earlier: Mapping[str, str] | None = None,
) -> str | Ask:
    """The reply to `dim` when the Q2 verdict (`failed`; None before Q2) already settles it, else what the model
    must decode. `earlier`: the replies decoded so far; a template Q6 is chosen among the strategies the Q5
    category and the Q4 severity admit (`corrections.admissible`). Shared by the local decoder and the endpoint
    path, so both ask the same things."""
    if dim == "Q1":
        return Ask("actions")
    if dim == "Q2":
        return Ask("choose", Q2_OPTIONS)
    if dim == "Q6":  # consistent with Q2: no correction after "no failure"; after a failure an instruction,
        # not the no-correction sentence nor a closed-set reply (Yes/No/None/a number)
        if failed is False:
            return Q.NO_CORRECTION
        if q6_mode == "template":
            earlier = earlier or {}
            cat, sev = _option(earlier.get("Q5"), len(Category)), _option(earlier.get("Q4"), len(Severity))
            return Ask("choose", tuple(text for _, text in candidates(objects, cat, sev)), per_token=True)
        closed = (Q.NO_CORRECTION, Q.NO_FAILURE, "Yes", "No", *map(str, range(10)))
        return Ask("free", closed if failed else ())
    if failed is False:
        return Q.NO_FAILURE
    return Ask("choose", numbered_options(dim, frames))


def _option(reply: str | None, n: int) -> int | None:
    """A closed-set reply as its option number (1..n), or None (not asked, "None", or out of range)."""
    return int(reply) if reply and reply.isdigit() and 1 <= int(reply) <= n else None


def asked_dims(dims: Collection[str], q6_mode: str) -> set[str]:
    """The dimensions to decode for a request of `dims`: Q2 always (the others follow its verdict), and Q4 and Q5
    with a template Q6 (the correction is chosen among the strategies the answered severity and category admit)."""
    out = set(dims) | {"Q2"}
    if q6_mode == "template" and "Q6" in out:
        out |= {"Q4", "Q5"}
    return out


@dataclass
class DiagnosisRequest:
    """One grid (or per-view keyframe lists) for `analyze_batch`, with the arguments `analyze` takes."""

    grid: Any
    task: str = ""
    frames: int | None = None
    objects: Sequence[str] = ()


def batch_settings(
    n: int,
    tasks: Sequence[str],
    frames: Sequence[int | None] | None,
    objects: Sequence[Sequence[str]] | None,
    dims: Sequence[Collection[str]] | None,
) -> tuple[list[int | None], list[Sequence[str]], list[Collection[str]]]:
    """`answers_batch`'s per-grid settings with their defaults (shared by the local and the endpoint analyzer)."""
    fr, ob, di = list(frames or [None] * n), list(objects or [()] * n), list(dims or [Q.DIMENSIONS] * n)
    if not len(tasks) == len(fr) == len(ob) == len(di) == n:
        raise ValueError("answers_batch: images, tasks, frames, objects and dims differ in length")
    return fr, ob, di


def check_threshold(value: Any) -> float:
    """An operating point on P(failure): a number in (0, 1)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 < float(value) < 1.0:
        raise ValueError(f"threshold: expected a number between 0 and 1 (exclusive), got {value!r}")
    return float(value)


def load_checkpoint(
    path: str | Path, dtype: Any, device: str | None, max_model_gb: float | None, kwargs: dict[str, Any]
) -> tuple[Any, Any]:
    """FailureAnalyzer.from_pretrained's model and processor, on `device` (default: cuda when there is one); the
    analyzer's `kwargs` gain what the checkpoint's manifest names (its grid, and `fit`; its option biases and
    failure score) unless the caller set them."""
    import torch

    from labrobfail_vlm.config import ConfigError
    from labrobfail_vlm.model.loading import load_model, load_processor
    from labrobfail_vlm.train.checkpoint import (
        is_finetuned,
        load_finetuned,
        read_manifest,
        trained_grid,
        validate_checkpoint,
    )

    validate_checkpoint(path, "model.path", max_model_gb, dtype)
    model = load_finetuned(path, dtype, max_model_gb) if is_finetuned(path) else load_model(path, dtype, max_model_gb)
    dev = device or ("cuda" if torch.cuda.is_available() else "cpu")
    if "grid" not in kwargs and (grid := trained_grid(path)) is not None:
        kwargs["grid"] = grid
        kwargs.setdefault("fit", True)
    if is_finetuned(path):
        man = read_manifest(Path(path), "model.path")
        try:
            if "option_bias" not in kwargs:
                kwargs["option_bias"] = check_option_bias(man.get("option_bias"))
            if "failure_score" not in kwargs:
                kwargs["failure_score"] = check_failure_score(man.get("failure_score", "q2"))
        except ValueError as e:
            raise ConfigError(f"model.path: {Path(path) / 'labrobfail.json'}: {e}") from None
    return model.to(dev), load_processor(path)


def choose_biased(
    decoder: Any, pre: Any, asks: Sequence[Ask], bias: Sequence[float]
) -> tuple[list[str], list[list[float]]]:
    """A closed failure-only question for each row of `pre`: the option chosen with the dimension's option `bias`,
    and every option's log-likelihood (without it)."""
    scores = decoder.option_scores_rows(pre, [a.options for a in asks], [a.per_token for a in asks])
    return [a.options[biased_choice(s, bias)] for a, s in zip(asks, scores)], scores


class FailureAnalyzer:
    """`q6_mode`: "free" (greedy text) or "template" (the most likely entry of the paper's correction-strategy
    table among the strategies of the answered Q5 category, placeholders filled from the `objects` given to
    `analyze`, so every correction maps to primitives and agrees with the diagnosis).
    `threshold`: Q2 answers "Yes" (a failure, and Q3-Q6 are asked as one) when P(failure) >= threshold; 0.5 is
    the decoder's argmax, a lower value makes a supervisor intervene earlier. `option_bias`: per closed failure-only
    question, a bias per option added to its log-likelihood before the argmax (labrobfail_vlm.option_bias; a
    checkpoint's labrobfail.json may carry one, fitted on validation by labrobfail-calibrate). `failure_score`:
    how P(failure) is read (FAILURE_SCORES; a checkpoint's labrobfail.json may name one)."""

    fit_grid = False  # subclasses that answer over HTTP (EndpointAnalyzer) take the grid as given

    def __init__(
        self,
        model: Any,
        processor: Any,
        grid: GridConfig = GridConfig(),
        q6_mode: str = "free",
        threshold: float = 0.5,
        fit: bool = False,
        option_bias: Mapping[str, Sequence[float]] | None = None,
        failure_score: str = "q2",
    ):
        from labrobfail_vlm.decoding import Decoder

        if q6_mode not in Q6_MODES:
            raise ValueError(f"q6_mode: expected one of {', '.join(Q6_MODES)}, got {q6_mode!r}")
        self.q6_mode = q6_mode
        self.threshold = check_threshold(threshold)
        self.option_bias = check_option_bias(option_bias)
        self.failure_score = check_failure_score(failure_score)
        self.model, self.processor = model.eval(), processor
        self.processor.tokenizer.padding_side = "left"
        self.decoder = Decoder(self.model, processor)
        self.grid = grid  # the layout the model was trained on: --frames grids and the Q3 range follow it
        self.fit_grid = fit  # another size brought to `grid` or refused (grid.fit_grid); on: the checkpoint names it
        self.num_frames, self.time_axis, self.index = grid.max_frames, grid.time_axis, grid.draw_index
        self._ids_checked = False

    @classmethod
    def from_pretrained(
        cls,
        path: str | Path,
        dtype: Any = None,
        device: str | None = None,
        max_model_gb: float | None = None,
        **kwargs: Any,
    ) -> "FailureAnalyzer":
        """`max_model_gb`: the model memory budget (default $LABROBFAIL_MAX_MODEL_GB, else half the machine's
        memory). The directory is validated before any tensor is built (train.checkpoint.validate_checkpoint): a
        bad or oversized checkpoint is a one-line ConfigError, not an out-of-memory kill."""
        model, processor = load_checkpoint(path, dtype, device, max_model_gb, kwargs)
        return cls(model, processor, **kwargs)

    # ---- prompts -----------------------------------------------------------------------------------------
    def _prompt(self, dim: str, task: str, variant: int = 0) -> str:
        from labrobfail_vlm.train.data import messages

        q = Q.question_text(dim, variant, task, self.time_axis, self.index)
        return self.processor.apply_chat_template(messages(q), tokenize=False, add_generation_prompt=True)

    def _decode(self, pre: Any, plans: Sequence[str | Ask | None]) -> list[str | None]:
        """Carry out one plan per row of `pre`, one kind of answer at a time (its rows decoded in lockstep)."""
        d = self.decoder
        out = [p if isinstance(p, str) else None for p in plans]
        for kind in ("choose", "actions", "free"):
            rows = [i for i, p in enumerate(plans) if isinstance(p, Ask) and p.kind == kind]
            if not rows:
                continue
            sub = pre if len(rows) == len(plans) else d.select(pre, rows)
            asks = [plans[i] for i in rows]
            if kind == "choose":
                got = d.choose_rows(sub, [a.options for a in asks], [a.per_token for a in asks])
            elif kind == "actions":
                got = d.actions_rows(sub, [True] * len(rows))
            else:
                got = [d.text(t or []) for t in d.free_tokens_rows(sub, [a.options for a in asks], [True] * len(rows))]
            for i, g in zip(rows, got):
                out[i] = g
        return out

    def _answer(
        self,
        dim: str,
        pre: Any,
        failed: bool | None,
        frames: int,
        objects: Sequence[str] = (),
        earlier: Mapping[str, str] | None = None,
    ) -> str:
        """One reply; a closed failure-only one's option scores go into `earlier` when it is the Answers being built
        (the six-prompt path keeps them as the one-pass path does)."""
        plan = plan_reply(dim, failed, frames, objects, self.q6_mode, earlier)
        if dim in BIASED_DIMS and isinstance(plan, Ask):
            (reply,), (scores,) = choose_biased(self.decoder, pre, [plan], self.option_bias.get(dim, ()))
            if isinstance(earlier, Answers):
                earlier.option_scores[dim] = scores
            return reply
        return str(self._decode(pre, [plan])[0])

    def _prefixes(self, image: Image.Image, prompts: dict[str, str]) -> Iterator[tuple[str, Any]]:
        """Six-prompt mode (the reference path): (dimension, model state after its whole prompt, image included)."""
        for dim, p in prompts.items():
            yield dim, self.decoder.prefill(dict(self.processor(text=[p], images=[image], return_tensors="pt")))

    def answers(
        self,
        image: Image.Image,
        task: str,
        one_pass: bool = True,
        frames: int | None = None,
        objects: Sequence[str] = (),
        dims: Collection[str] = Q.DIMENSIONS,
    ) -> dict[str, str]:
        """The replies to `dims`, and to what they depend on (`asked_dims`)."""
        if one_pass:
            return self.answers_batch([image], [task], [frames], [objects], [dims])[0]
        frames = frames or self.num_frames
        need = asked_dims(dims, self.q6_mode)
        prompts = {dim: self._prompt(dim, task) for dim in Q.DIMENSIONS if dim in need}
        # the verdict first, from each question read's own prompt (a Q3-Q5 prefix is prefilled again below)
        reads = score_reads(self.failure_score, self.index)
        pres = self._prefixes(image, {key: self._prompt(dim, task, v) for key, dim, v in reads})
        p = float(np.mean([read_rows(self.decoder, dim, next(pres)[1], [frames], v)[0] for _, dim, v in reads]))
        (reply,) = verdicts([p], self.threshold)
        out = Answers()
        out.p_failure, failed = p, reply == "Yes"
        rest = self._prefixes(image, {d: t for d, t in prompts.items() if d != "Q2"})
        for dim in prompts:  # the replies in the questions' order
            out[dim] = reply if dim == "Q2" else self._answer(dim, next(rest)[1], failed, frames, objects, out)
        return out

    def answers_batch(
        self,
        images: Sequence[Image.Image],
        tasks: Sequence[str],
        frames: Sequence[int | None] | None = None,
        objects: Sequence[Sequence[str]] | None = None,
        dims: Sequence[Collection[str]] | None = None,
        max_batch: int | None = None,
    ) -> list[dict[str, str]]:
        """`answers` (one pass) for many grids: grids of one size are decoded together, `max_batch` at a time, with
        the same replies as one at a time. Per-grid `frames`, `objects` and `dims` as in `answers`."""
        n = len(images)
        frames, objects, dims = batch_settings(n, tasks, frames, objects, dims)
        groups: dict[tuple[int, int], list[int]] = {}
        for i, img in enumerate(images):  # one size, one token count: rows without padding to each other
            groups.setdefault(img.size, []).append(i)
        step = max(1, max_batch or n)
        out: list[dict[str, str]] = [{} for _ in range(n)]
        for idx in groups.values():
            for c in range(0, len(idx), step):
                part = idx[c : c + step]
                got = self._answers_rows(
                    [images[i] for i in part],
                    [tasks[i] for i in part],
                    [frames[i] or self.num_frames for i in part],
                    [objects[i] for i in part],
                    [dims[i] for i in part],
                )
                for i, a in zip(part, got):
                    out[i] = a
        return out

    def _answers_rows(
        self,
        images: list[Image.Image],
        tasks: list[str],
        frames: list[int],
        objects: list[Sequence[str]],
        dims: list[Collection[str]],
    ) -> list[Answers]:
        """One pass over a batch: each grid's image and preamble are prefilled once (one forward for the batch);
        a question's own tokens are fed only for the rows whose reply needs the model (Q3-Q6 follow Q2)."""
        d = self.decoder
        needs = [asked_dims(ds, self.q6_mode) for ds in dims]
        reads = score_reads(self.failure_score, self.index)  # their prompts are fed to every row before the verdict
        prompts = [
            {dim: self._prompt(dim, t) for dim in Q.DIMENSIONS if dim in need}
            | {key: self._prompt(dim, t, v) for key, dim, v in reads}
            for t, need in zip(tasks, needs)
        ]
        import torch

        # one image per call: the image processor on a list of large grids is ~3x slower per image (measured)
        one = [self.processor.image_processor(images=[im], return_tensors="pt") for im in images]
        px = {k: torch.cat([o[k] for o in one]) for k in ("pixel_values", "image_grid_thw")}
        visual = (px["image_grid_thw"].prod(-1) // self.processor.image_processor.merge_size**2).tolist()
        ids = [{dim: d.prompt_ids(p, v) for dim, p in pr.items()} for pr, v in zip(prompts, visual)]
        if not self._ids_checked:  # once: the hand-made token ids equal the processor's
            ref = self.processor(text=[prompts[0]["Q2"]], images=images[:1], return_tensors="pt")["input_ids"][0]
            if ref.tolist() != ids[0]["Q2"]:
                raise ValueError("analyzer: prompt tokenization differs from the processor's")
            self._ids_checked = True
        lcp = [common_prefix_len(list(x.values())) for x in ids]
        pre = d.prefill_rows([x["Q2"][:k] for x, k in zip(ids, lcp)], px["pixel_values"], px["image_grid_thw"])
        out = [Answers() for _ in images]
        failed: list[bool | None] = [None] * len(images)
        for dim in Q.DIMENSIONS:
            plans = [
                plan_reply(dim, failed[i], frames[i], objects[i], self.q6_mode, out[i]) if dim in needs[i] else None
                for i in range(len(images))
            ]
            replies: list[str | None] = [p if isinstance(p, str) else None for p in plans]
            rows = [i for i, p in enumerate(plans) if isinstance(p, Ask)]
            if rows:  # only these rows are fed the question: the others' replies follow from Q2
                base = pre if len(rows) == len(images) else d.select(pre, rows)
                sel = [out[i] for i in rows]
                if dim == "Q2":
                    got = self._verdict_rows(
                        base, [ids[i] for i in rows], [lcp[i] for i in rows], [frames[i] for i in rows], sel
                    )
                else:
                    q, _ = d.extend_rows(base, [ids[i][dim][lcp[i] :] for i in rows])
                    got = self._reply_rows(dim, q, [plans[i] for i in rows], sel)  # type: ignore[misc]
                    d.rewind(q, base)
                for i, r in zip(rows, got):
                    replies[i] = r
            for i, r in enumerate(replies):
                if r is not None:
                    out[i][dim] = r
            if dim == "Q2":
                failed = [o.get("Q2") == "Yes" for o in out]
        return out

    def _verdict_rows(
        self, base: Any, ids: list[dict[str, list[int]]], lcp: list[int], frames: list[int], out: list[Answers]
    ) -> list[str]:
        """Q2's reply for each row of `base` (the rows' shared preamble): each question read's prompt fed in turn
        and rewound, their scores averaged (`failure_score.shared_rows`); P(failure) goes into the row's Answers."""
        probs = shared_rows(self.decoder, base, ids, lcp, frames, score_reads(self.failure_score, self.index))
        for a, p in zip(out, probs):
            a.p_failure = p
        return verdicts(probs, self.threshold)

    def _reply_rows(self, dim: str, q: Any, plans: list[Ask], out: list[Answers]) -> list[str | None]:
        """`dim`'s reply for each row of `q` (the model after the question); a closed failure-only question's
        option scores go into the row's Answers."""
        if dim not in BIASED_DIMS:
            return self._decode(q, plans)
        got, scores = choose_biased(self.decoder, q, plans, self.option_bias.get(dim, ()))
        for a, sc in zip(out, scores):
            a.option_scores[dim] = sc
        return list(got)

    def _prepare(
        self, grid_or_frames: Image.Image | np.ndarray | Sequence[Sequence[Any]], task: str, frames: int | None
    ) -> tuple[Image.Image, str, int | None]:
        """(RGB grid, task text, keyframes shown) from a grid image or per-view keyframe lists."""
        if isinstance(grid_or_frames, (Image.Image, np.ndarray)):
            img = grid_or_frames if isinstance(grid_or_frames, Image.Image) else Image.fromarray(grid_or_frames)
            img = fit_grid(img, self.grid) if self.fit_grid else img
        else:
            frames = frames or min(len(grid_or_frames[0]), self.num_frames)
            img = frames_to_grid(grid_or_frames, self.grid)
        return img.convert("RGB"), task or "a laboratory manipulation task", frames

    def analyze_video(
        self, videos: Sequence[str | Path], task: str = "", keyframes: str = "uniform", **kwargs: Any
    ) -> Diagnosis:
        """One video per camera view, in the order of the grid's view bands (the views the model was trained on,
        e.g. front then side): the keyframes picked by labrobfail_vlm.video (`uniform` in time or by `motion`),
        then `analyze` on the grid they make."""
        from labrobfail_vlm.video import read_keyframes

        return self.analyze(read_keyframes(videos, self.num_frames, keyframes), task, **kwargs)

    def analyze_batch(
        self, requests: Sequence[DiagnosisRequest | Image.Image], one_pass: bool = True, max_batch: int | None = None
    ) -> list[Diagnosis]:
        """`analyze` for many grids at once (batched decoding, `max_batch` grids per forward), same answers."""
        reqs = [r if isinstance(r, DiagnosisRequest) else DiagnosisRequest(r) for r in requests]
        ready = [self._prepare(r.grid, r.task, r.frames) for r in reqs]
        if one_pass:
            ans = self.answers_batch(
                [g for g, _, _ in ready],
                [t for _, t, _ in ready],
                [f for *_, f in ready],
                [r.objects for r in reqs],
                max_batch=max_batch,
            )
        else:
            ans = [self.answers(g, t, False, f, r.objects) for (g, t, f), r in zip(ready, reqs)]
        return [self.analyze(g, t, frames=f, objects=r.objects, answers=a) for (g, t, f), r, a in zip(ready, reqs, ans)]

    def analyze(
        self,
        grid_or_frames: Image.Image | np.ndarray | Sequence[Sequence[Any]],
        task: str = "",
        one_pass: bool = True,
        frames: int | None = None,
        objects: Sequence[str] = (),
        answers: dict[str, str] | None = None,
    ) -> Diagnosis:
        """`objects`: the scene's object and place names (used by q6_mode="template"); `answers`: replies already
        decoded for this grid (analyze_batch)."""
        img, task, frames = self._prepare(grid_or_frames, task, frames)
        return diagnosis_of(answers or self.answers(img, task, one_pass, frames, objects), task, objects)
