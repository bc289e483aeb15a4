"""Dense per-frame targets for the vision tower's pretraining, read from simulator state (never from the injection).

For each grid frame k (the state at the sample its images show, `image_samples(trace)[picks[k]]`) and each
camera view, two kinds of target:

  cell targets   one value per frame, 1 / 0, or -1 where the task has no such thing (no oven, no liquid, ...):
                 CELL_TARGETS below, e.g. "a task object is held", "every goal of the task holds by now",
                 "a failure has happened by this frame" (the labeler's failure keyframe, as the grid shows it)
  point targets  where things are in each view's picture: the pixel positions of the gripper, the task objects
                 and the places task objects must reach (TOKEN_TARGETS), projected with the recorded camera
                 matrices (`Episode.cameras`); the trainer turns them into "which 32 x 32 px token holds it"

Task objects are the task's own movables (the trace's `<role>.pos` columns): distractors are not in the trace.
"""

from __future__ import annotations

import json
from typing import Any, Sequence

import numpy as np

from sim_backends.goals import FALLEN_TILT, GOALS, OFF_BENCH, UPRIGHT_TILT, tilt
from sim_backends.labeler import OPEN_WIDTH, POSE_ERR, SPILL_PARTICLES, spilled
from sim_backends.schema import image_samples, movables, trace_at
from sim_backends.types import rotation_angle

CELL_TARGETS: tuple[str, ...] = (
    "held",  # a task object is in contact with the fingers and off its resting height
    "lifted",  # a task object is more than 3 cm above where it started
    "tipped",  # a task vessel leans more than 0.35 rad
    "fallen",  # a task object is off the bench or lying on its side
    "at_goal",  # every "at" goal (object at its place) holds; -1: the task has none
    "door_open",  # the oven door is open more than 0.3 rad; -1: no oven
    "button_pressed",  # the button has been pressed by now; -1: no button
    "liquid_in_dest",  # the poured liquid has reached its vessel; -1: no liquid goal
    "spilled",  # liquid has landed outside every vessel; -1: no liquid
    "gripper_closed",  # the fingers are closed (opening under 6 cm)
    "hand_twisted",  # the hand is turned more than 0.3 rad away from the plan's orientation for this keyframe
    "arm_moved",  # the hand moved more than 2 cm since the previous grid frame; -1 on the first
    "object_moved",  # a task object moved more than 2 cm since the previous grid frame; -1 on the first
    "goals_hold",  # every goal of the task holds at this frame
    "failed_by_now",  # a failure has happened by this frame (the grid frame of the labeler's failure keyframe)
)
TOKEN_TARGETS: tuple[str, ...] = ("gripper", "object", "goal_place")
LIFT, MOVED, DOOR_OPEN, CLOSED_WIDTH = 0.03, 0.02, 0.3, 0.06


def _cell_values(
    trace: dict[str, Any],
    meta: dict[str, Any],
    j: int,
    prev: int | None,
    failed: bool,
    plan_quat: Sequence[float] | None,
) -> list[float]:
    objs = movables(trace, meta)
    vessels = [o for o in objs if meta["objects"][o]["kind"] == "vessel"]
    pos = {o: np.asarray(trace[f"{o}.pos"][j], float) for o in objs}
    home = {o: float(meta["objects"][o]["home"][2]) for o in objs}
    bench = float(meta["bench_top"])
    upto = trace_at(trace, j)
    goals = meta["goals"]

    def goal_kinds(*kinds: str) -> float:
        gs = [g for g in goals if g["kind"] in kinds]
        return -1.0 if not gs else float(all(GOALS[g["kind"]](upto, meta, g) for g in gs))

    ovens = [o for o, info in meta["objects"].items() if info["kind"] == "oven" and f"{o}.q" in trace]
    buttons = [o for o, info in meta["objects"].items() if info["kind"] == "button" and f"{o}.q" in trace]
    liquid = "liquid.outside" in trace
    moved = lambda a, b: float(np.linalg.norm(np.asarray(a, float) - np.asarray(b, float)) > MOVED)  # noqa: E731
    return [
        float(any(trace[f"{o}.contacts"][j] >= 1 and pos[o][2] > home[o] + 0.01 for o in objs)),
        float(any(pos[o][2] > home[o] + LIFT for o in objs)),
        float(any(tilt(trace[f"{o}.quat"][j]) > UPRIGHT_TILT for o in vessels)),
        float(
            any(pos[o][2] < bench + OFF_BENCH for o in objs)
            or any(tilt(trace[f"{o}.quat"][j]) > FALLEN_TILT for o in vessels)
        ),
        goal_kinds("at"),
        float(any(trace[f"{o}.q"][j] > DOOR_OPEN for o in ovens)) if ovens else -1.0,
        goal_kinds("button") if buttons else -1.0,
        goal_kinds("liquid"),
        float(spilled(trace, j) >= SPILL_PARTICLES) if liquid else -1.0,
        float(trace["width"][j] < min(CLOSED_WIDTH, OPEN_WIDTH)),
        -1.0 if plan_quat is None else float(rotation_angle(trace["ee_quat"][j], plan_quat) > POSE_ERR),
        -1.0 if prev is None else moved(trace["ee_pos"][j], trace["ee_pos"][prev]),
        -1.0
        if prev is None or not objs
        else float(any(moved(trace[f"{o}.pos"][j], trace[f"{o}.pos"][prev]) for o in objs)),
        float(all(GOALS[g["kind"]](upto, meta, g) for g in goals)),
        float(failed),
    ]


def project(points: np.ndarray, matrices: Sequence[float], size: int) -> np.ndarray:
    """World points (N, 3) -> pixel (x, y) in a `size` px square image, NaN behind the camera. `matrices`: the
    view then the projection matrix, OpenGL column-major (as PyBullet returns them)."""
    view = np.asarray(matrices[:16], float).reshape(4, 4).T
    proj = np.asarray(matrices[16:32], float).reshape(4, 4).T
    h = np.c_[points, np.ones(len(points))] @ (proj @ view).T
    with np.errstate(divide="ignore", invalid="ignore"):
        ndc = h[:, :3] / h[:, 3:4]
    px = np.c_[(ndc[:, 0] + 1) / 2 * size, (1 - ndc[:, 1]) / 2 * size]
    px[h[:, 3] <= 0] = np.nan
    return px


MAX_POINTS = 4  # per token target and view: the gripper is one point, task objects and places up to four


def row_targets(
    row: dict[str, Any], picks: Sequence[int], views: Sequence[int], failure_frame: int | None, image_size: int
) -> tuple[np.ndarray, np.ndarray]:
    """(cells (F, V, len(CELL_TARGETS)), points (F, V, len(TOKEN_TARGETS), MAX_POINTS, 2)) for the grid frames
    `picks` (executed keyframe indices) of shard row `row`, in the camera views `views` (indices into its
    camera_names). `failure_frame`: the 1-based grid frame where the labeled failure first shows (None: a
    success). `points` are pixel (x, y) positions in the view's `image_size` px image, NaN where there is no such
    point, it is behind the camera, or the view's camera matrices were not recorded; the trainer turns them into
    token targets after it has shifted and scaled the picture (labrobfail_vlm/train/tower.py)."""
    trace, meta = json.loads(row["state_trace"]), json.loads(row["task_meta"])
    cams = json.loads(row.get("cameras") or "[]")
    objs = movables(trace, meta)
    places = sorted({g["xy"] for g in meta["goals"] if g["kind"] == "at"})
    cells = np.zeros((len(picks), len(views), len(CELL_TARGETS)), np.float32)
    points = np.full((len(picks), len(views), len(TOKEN_TARGETS), MAX_POINTS, 2), np.nan, np.float32)
    prev = None
    plan = {k["name"]: k["quat"] for k in meta["nominal"]}
    shots = image_samples(trace)
    for f, kf in enumerate(picks):
        j = shots[kf]
        failed = failure_frame is not None and f + 1 >= failure_frame
        name = meta["executed"][kf] if kf < len(meta["executed"]) else None
        cells[f, :, :] = _cell_values(trace, meta, j, prev, failed, plan.get(name))
        groups = [
            [trace["ee_pos"][j]],
            [trace[f"{o}.pos"][j] for o in objs],
            [[*meta["places"][p][:2], meta["bench_top"]] for p in places],
        ]
        for v_out, v in enumerate(views):
            mats = cams[v][kf] if v < len(cams) and kf < len(cams[v]) else None
            if not mats:
                continue
            for c, pts in enumerate(groups):
                pts = pts[:MAX_POINTS]
                if pts:
                    points[f, v_out, c, : len(pts)] = project(np.asarray(pts, float), mats, image_size)
        prev = j
    return cells, points
