"""VQA annotation: one shard row (a labeled episode) -> its keyframe grid and six question-answer records.

Answers come from the simulator's state-derived labels and task metadata (never from
the injected perturbation); question wording and answer formats come from
labrobfail_vlm.questions, corrections from labrobfail_vlm.corrections, the grid from
labrobfail_vlm.grid. `check_record` is the paper's rule-based filter.
"""

from __future__ import annotations

import io
import json
import re
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
from PIL import Image

from labrobfail_data.facts import aux_records, frame_facts
from labrobfail_vlm import questions as Q
from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.corrections import Context, correction
from labrobfail_vlm.grid import GridConfig, build_grid, frame_for_keyframe, whole_grid_picks
from labrobfail_vlm.taxonomy import ATOMIC_ACTIONS, Category, Severity
from sim_backends.failure_context import failure_context
from sim_backends.labeler import derive_labels, severity
from sim_backends.robot_signals import dense_table, frame_times, irreversible, robot_signals
from sim_backends.schema import trace_until

# What a prefix grid may be asked (prefix.questions). Q4 is not: severity is a rule on the final state (a door
# left open, a vessel lying on its side at the end), which a prefix does not show yet.
PREFIX_QUESTIONS = ("Q2", "Q3", "Q5", "Q6")


@dataclass
class Annotated:
    trajectory: str  # unique id across runs: "<variant>-<episode_id>"
    group: str  # split unit: a success/failure pair and its shared initial state
    variant: str
    image_name: str
    grid: Image.Image | None  # the keyframe grid; None once the builder has written it to image_name
    records: list[dict[str, Any]]
    meta: dict[str, Any] = field(default_factory=dict)  # what the review page and stats show
    prefixes: list["Annotated"] = field(default_factory=list)  # prefix grids of the first k keyframes
    aux: list[dict[str, Any]] = field(default_factory=list)  # per-frame fact records (training split only)
    dense: np.ndarray | None = None  # the robot's signals at every trace sample (robot_signals.dense_table)


def q6_keep(ctx: Context | None, text: str) -> list[str]:
    """The names a (reworded) correction must keep: the objects it acts on, as filled from metadata."""
    return [w for w in ((ctx.target, ctx.destination, ctx.source) if ctx else ()) if w in text]


def row_images(row: dict[str, Any], views: Sequence[str] | None) -> list[list[bytes]]:
    """The row's images `[view][keyframe]` of the named camera views, in that order (None: every view)."""
    if views is None:
        return row["images"]
    names = list(row.get("camera_names") or [])
    missing = [v for v in views if v not in names]
    if missing:
        raise ConfigError(
            f"views: episode {row['episode_id']} has views {names}, not {missing} (generate with "
            "backend_kwargs.wrist=true for a wrist view)"
        )
    return [row["images"][names.index(v)] for v in views]


def decode_views(images: list[list[bytes]], picks: list[int]) -> list[list[Image.Image]]:
    if any(not view[i] for view in images for i in picks):  # b"": the generator's render_frames left it out
        raise ConfigError(
            "grid.max_frames: the shards hold no images of keyframes this grid shows; build with the "
            "generator's render_frames as grid.max_frames, or regenerate with render_frames=null"
        )
    return [[Image.open(io.BytesIO(view[i])).convert("RGB") for i in picks] for view in images]


def grid_picks(row: dict[str, Any], max_frames: int) -> list[int]:
    """The executed keyframes a grid of `max_frames` shows for this shard row."""
    kfs = json.loads(row["keyframes"])
    return whole_grid_picks([k["name"] for k in kfs], [k["segment"] for k in kfs], max_frames)


def grid_failure_frame(row: dict[str, Any], picks: list[int]) -> int | None:
    """The 1-based grid frame where the row's labeled failure first shows (None for a success)."""
    return None if row["success"] else frame_for_keyframe(picks, int(row["failure_keyframe"]))


def _qa_record(rid: str, image: str, question: str, answer: str) -> dict[str, Any]:
    """One ShareGPT/LLaVA record: the grid, one question and its answer."""
    return {
        "id": rid,
        "image": image,
        "images": [image],  # "images": LLaMA-Factory's column
        "conversations": [{"from": "human", "value": question}, {"from": "gpt", "value": answer}],
    }


def _answers(
    row: dict[str, Any], meta: dict[str, Any], trace: Any, picks: list[int]
) -> tuple[dict[str, str], int | None, Context | None, str | None]:
    """The answers Q1, Q3-Q6 (Q2 follows its wording), the grid failure frame, the failure context and strategy."""
    answers: dict[str, str] = {"Q1": Q.format_actions(list(row["actions"]))}
    ctx, strategy = None, None
    if bool(row["success"]):
        answers.update(Q3=Q.NO_FAILURE, Q4=Q.NO_FAILURE, Q5=Q.NO_FAILURE, Q6=Q.NO_CORRECTION)
        frame = None
    else:
        frame = grid_failure_frame(row, picks)
        ctx = failure_context(row, meta, trace)
        strategy, fix = correction(ctx)
        answers.update(Q3=str(frame), Q4=str(int(row["severity"])), Q5=str(int(row["category"])), Q6=fix)
    return answers, frame, ctx, strategy


def _main_records(
    traj: str,
    image: str,
    task_name: str,
    answers: dict[str, str],
    success: bool,
    grid_cfg: GridConfig,
    rng: np.random.Generator,
) -> list[dict[str, Any]]:
    """The six records of a trajectory, each question's wording drawn from `rng` in Q.DIMENSIONS order."""
    records = []
    for dim in Q.DIMENSIONS:
        v = int(rng.integers(len(Q.VARIANTS[dim])))
        ans = Q.q2_answer(v, success) if dim == "Q2" else answers[dim]
        question = Q.question_text(dim, v, task_name, grid_cfg.time_axis, grid_cfg.draw_index)
        records.append(_qa_record(Q.record_id(traj, dim), image, question, ans))
    return records


def _trajectory_info(
    row: dict[str, Any],
    meta: dict[str, Any],
    traj: str,
    task_name: str,
    frame: int | None,
    picks: list[int],
    views: list[list[Image.Image]],
    strategy: str | None,
    keep: list[str],
) -> dict[str, Any]:
    """The trajectory's metadata: labels, sampled keyframes, strategy (what the review page and stats show)."""
    return {
        "trajectory": traj,
        "group": f"{row['variant']}-{row['pair_id']}",
        "scenario": row["scenario"],
        "task": task_name,
        "variant": row["variant"],
        "success": bool(row["success"]),
        "failure_type": row["failure_type"],
        "category": row["category"],
        "severity": row["severity"],
        "failure_keyframe": row["failure_keyframe"],
        "frame": frame,
        "frames": len(picks),
        "views": len(views),
        "sampled_keyframes": picks,
        "horizon": row["horizon"],
        "actions": list(row["actions"]),
        "evidence": row["evidence"],
        "strategy": strategy,
        # the scene's object and place names: what a robot stack knows, and what Q6's template mode fills in
        "objects": sorted(set(meta.get("labels", {}).values())),
        "q6_keep": keep,
    }


def annotate(
    row: dict[str, Any],
    grid_cfg: GridConfig,
    rng: np.random.Generator,
    prefix_cuts: int = 0,
    prefix_rng: np.random.Generator | None = None,
    aux: int = 0,
    cut_frame: int | None = None,
    *,
    prefix_questions: Sequence[str],
    views: Sequence[str] | None = None,
) -> Annotated:
    """`prefix_cuts` > 0 adds that many prefix grids, each with a record per `prefix_questions`
    (`prefix_records`); `aux` > 0 that many per-frame fact records (labrobfail_data/facts.py). Both draw from
    `prefix_rng`, so the six main records are the same with or without them. `cut_frame`: the failure frame the
    prefix cuts are placed around (None: this trajectory's own); the builder passes a pair's so that twins are cut
    at the same keyframes."""
    meta = json.loads(row["task_meta"])
    trace = json.loads(row["state_trace"])
    picks = grid_picks(row, grid_cfg.max_frames)
    views = decode_views(row_images(row, views), picks)
    grid = build_grid(views, grid_cfg)
    traj = f"{row['variant']}-{row['episode_id']}"
    image = f"images/{traj}.png"
    task_name = meta.get("description") or row["scenario"].replace("_", " ")
    success = bool(row["success"])
    answers, frame, ctx, strategy = _answers(row, meta, trace, picks)
    records = _main_records(traj, image, task_name, answers, success, grid_cfg, rng)
    info = _trajectory_info(row, meta, traj, task_name, frame, picks, views, strategy, q6_keep(ctx, answers["Q6"]))
    info |= onset(row, trace, meta) | irreversible(trace, meta)
    dense = dense_table(trace, row["keyframes"])
    info |= {
        "frame_times_s": frame_times(trace, picks),
        "robot_signals": robot_signals(trace, row["keyframes"], picks, dense),
    }
    ann = Annotated(traj, info["group"], row["variant"], image, grid, records, info)
    ann.dense = dense.astype(np.float32)  # as the file stores it; a full dataset's tables held until it is written
    if prefix_cuts > 0:

        def context_at(k: int) -> Context:  # the failure as it stands once grid frame k has been shown
            until = trace_until(trace, picks[k - 1])
            return failure_context(row, meta, until, severity(until, meta, row["failure_type"]) == Severity.FATAL)

        ann.prefixes = prefix_records(
            ann,
            views,
            grid_cfg,
            prefix_cuts,
            prefix_rng or rng,
            frame if cut_frame is None else cut_frame,
            prefix_questions,
            context_at,
        )
    if aux > 0:
        ann.aux = aux_records(
            traj,
            image,
            Q.preamble(task_name, grid_cfg.time_axis, grid_cfg.draw_index),
            frame_facts(trace, meta, picks),
            aux,
            prefix_rng or rng,
        )
    return ann


def onset(row: dict[str, Any], trace: dict[str, Any], meta: dict[str, Any]) -> dict[str, Any]:
    """A failure's onset, the first keyframe (and sim time) its state signature shows, re-derived from the trace by
    the labeler as every label is (shards before 29 Nov do not store `onset_s`). None for a success, and for a
    failure whose stored keyframe the labeler no longer derives from its trace (a shard of an older labeler): no
    onset is guessed."""
    lab = None if row["success"] else derive_labels(trace, meta)
    if lab is None or lab.failure_keyframe != row["failure_keyframe"]:
        return {"onset_keyframe": None, "onset_s": None}
    return {"onset_keyframe": lab.failure_keyframe, "onset_s": lab.onset_s}


def prefix_cut_points(frames: int, failure_frame: int | None, n: int, rng: np.random.Generator) -> list[int]:
    """Up to n prefix lengths k in [1, frames - 1]. For a failure, one cut before its frame and one at or after
    it come first (when they exist; with n = 1, one of the two at random), so prefixes teach "not yet" and "now"."""
    cuts = list(range(1, frames))
    first: list[int] = []
    if failure_frame is not None:
        for side in ([k for k in cuts if k < failure_frame], [k for k in cuts if k >= failure_frame]):
            if side:
                first.append(int(rng.choice(side)))
    if len(first) > n:  # fewer cuts than sides: a fair draw of which side
        first = [first[int(rng.integers(len(first)))]]
    rest = [k for k in cuts if k not in first]
    more = [int(k) for k in rng.permutation(rest)] if rest else []
    return sorted((first + more)[:n])


def prefix_records(
    ann: Annotated,
    views: list[list[Image.Image]],
    grid_cfg: GridConfig,
    n: int,
    rng: np.random.Generator,
    cut_frame: int | None,
    questions: Sequence[str],
    context_at: Callable[[int], Context],
) -> list[Annotated]:
    """Prefix grids for online supervision: the first k keyframes shown, later cells blank. Q2 asks whether a
    failure has shown up yet (the labeled failure frame is <= k), Q3 the frame when it has, else None; Q5 its
    category; Q6 its correction, from the failure context as it stands at frame k (`context_at`: fallen or
    fatal by then, not later). The cuts are placed around `cut_frame`; the answers always come from this
    trajectory's own label."""
    info, out = ann.meta, []
    for k in prefix_cut_points(info["frames"], cut_frame, n, rng):
        failed = info["frame"] is not None and info["frame"] <= k
        traj = f"{ann.trajectory}-p{k}"
        image = f"images/{traj}.png"
        ctx = context_at(k) if failed and "Q6" in questions else None
        fix = correction(ctx) if ctx else (None, "")
        answers = (
            {"Q3": str(info["frame"]), "Q5": str(info["category"]), "Q6": fix[1]}
            if failed
            else {"Q3": Q.NO_FAILURE, "Q5": Q.NO_FAILURE, "Q6": Q.NO_CORRECTION}
        )
        records = []
        for dim in questions:  # Q2 and Q3 draw first, so the default prefixes are what they always were
            v = int(rng.integers(len(Q.VARIANTS[dim])))
            ans = Q.q2_answer(v, not failed) if dim == "Q2" else answers[dim]
            question = Q.question_text(dim, v, info["task"], grid_cfg.time_axis, grid_cfg.draw_index)
            records.append(_qa_record(Q.record_id(traj, dim), image, question, ans))
        meta = {
            **{k: v for k, v in info.items() if k != "robot_signals"},  # the online bench reads whole trajectories'
            "trajectory": traj,
            "prefix_of": ann.trajectory,
            "visible": k,
            "success": not failed,
            "frame": info["frame"] if failed else None,
            "failure_type": info["failure_type"] if failed else None,
            "category": info["category"] if failed else None,
            "severity": info["severity"] if failed else None,
            "onset_keyframe": info.get("onset_keyframe") if failed else None,
            "onset_s": info.get("onset_s") if failed else None,
        }
        if "Q6" in questions:  # the prefix's own correction (its trajectory's may follow from a later fall)
            meta.update(strategy=fix[0], q6_keep=q6_keep(ctx, fix[1]))
        out.append(
            Annotated(traj, ann.group, ann.variant, image, build_grid(views, grid_cfg, visible=k), records, meta)
        )
    return out


# ---- the rule-based filter -------------------------------------------------------------------------------
_INT = re.compile(r"^\d+$")


def check_record(rec: Any, info: dict[str, Any]) -> str | None:
    """None if the record is well-formed and consistent with the metadata, else the reason to drop it."""
    try:
        rid, conv = rec["id"], rec["conversations"]
        human, gpt = conv
        if not (
            isinstance(rid, str)
            and isinstance(rec["image"], str)
            and human["from"] == "human"
            and gpt["from"] == "gpt"
            and isinstance(human["value"], str)
            and isinstance(gpt["value"], str)
        ):
            return "malformed"
    except (KeyError, TypeError, ValueError):
        return "malformed"
    q, a = human["value"], gpt["value"].strip()
    if not q.startswith("<image>\n") or q.count("<image>") != 1 or not a:
        return "malformed"
    dim = rid.rsplit("_", 1)[-1]
    ok = info["success"]
    if Q.is_aux(dim):  # a per-frame fact (labrobfail_data/facts.py), derived from the trace
        return None if a in ("Yes", "No") and q.endswith("(Yes/No)") else "malformed"
    if dim == "Q1":
        acts = [s.strip() for s in a.split(",")]
        return None if acts == info["actions"] and set(acts) <= set(ATOMIC_ACTIONS) else "inconsistent"
    if dim == "Q2":
        if a not in ("Yes", "No"):
            return "malformed"
        v = Q.q2_variant(q)
        if v is None:  # Q2 is never paraphrased: its wording decides what "Yes" means
            return "malformed"
        return None if a == Q.q2_answer(v, ok) else "inconsistent"
    if dim == "Q3":
        if ok:
            return None if a == Q.NO_FAILURE else "inconsistent"
        if not _INT.match(a) or not 1 <= int(a) <= info["frames"]:
            return "frame_out_of_range"
        return None if int(a) == info["frame"] else "inconsistent"
    if dim in ("Q4", "Q5"):
        if ok:
            return None if a == Q.NO_FAILURE else "inconsistent"
        hi, want = (len(Severity), info["severity"]) if dim == "Q4" else (len(Category), info["category"])
        if not _INT.match(a) or not 1 <= int(a) <= hi:
            return "malformed"
        return None if int(a) == int(want) else "inconsistent"
    if dim == "Q6":
        if ok:
            return None if a == Q.NO_CORRECTION else "inconsistent"
        if len(a.split()) < 4:
            return "malformed"
        return None if all(w.lower() in a.lower() for w in info.get("q6_keep", [])) else "inconsistent"
    return "malformed"
