"""ManiSkill task templates: a keyframe program over named roles plus the goals that define success.

A scenario (configs/tasks/maniskill.yaml) = environment (a stock ManiSkill task or the lab bench)
x template x layout. Template names match the PyBullet backend's where the task is the same
(pick_place, insert_tube, press_button, open_oven, close_oven, shake); goals use the predicates of
sim_backends/goals.py, so labels are derived exactly as on PyBullet.
"""

from __future__ import annotations

import math
from typing import Any

from sim_backends.maniskill.plan import Plan, yaw_of
from sim_backends.registry import register_task


def _grasp(plan: Plan, obj: str, p: dict[str, Any]) -> tuple:
    """The scenario's grasp of `obj` (params.grasp: side | cube | rod); returns the held orientation."""
    how = p.get("grasp", "side")
    if how == "side":
        plan.grasp_side(obj)
    elif how == "cube":
        plan.grasp_cube(obj)
    elif how == "rod":  # a rod standing upright: top-down, a little below its top
        o = plan.scene.objects[obj]
        plan.grasp_top(obj, 0.0, float(o.pos[2] + o.dims["length"] / 2 - 0.035), lift=o.dims["length"] * 0.75 + 0.02)
    else:
        raise ValueError(f"scenario: unknown grasp {how!r}; expected side, cube or rod")
    return plan.keyframes[-1].quat


def _retreat(p: dict[str, Any]) -> tuple[float, float, float]:
    return (-0.12, 0.0, 0.0) if p.get("grasp", "side") == "side" else (0.0, 0.0, 0.10)


@register_task("pick", backend="maniskill")
def pick(plan: Plan, p: dict[str, Any]) -> None:
    """The atomic pick (the recovery table's pick row): grasp, lift, hold."""
    _grasp(plan, "obj", p)
    plan.goal("held", object="obj")


@register_task("pick_place", backend="maniskill")
def pick_place(plan: Plan, p: dict[str, Any]) -> None:
    q = _grasp(plan, "obj", p)
    plan.place("obj", "target", q, retreat=_retreat(p))
    plan.goal_placed("obj", "target")


@register_task("stack", backend="maniskill")
def stack(plan: Plan, p: dict[str, Any]) -> None:
    q = _grasp(plan, "obj", {"grasp": "cube"})
    base = plan.scene.objects["base"]
    plan.place("obj", "base", q, surface=float(base.pos[2] + base.dims["height"] / 2))
    plan.goal_placed("obj", "base", tol=0.02)


@register_task("push", backend="maniskill")
def push(plan: Plan, p: dict[str, Any]) -> None:
    plan.push("obj", "target")
    plan.goal("at", object="obj", xy="target", tol=float(p.get("tol", 0.05)))
    plan.goal("upright", object="obj")


@register_task("stand_upright", backend="maniskill")
def stand_upright(plan: Plan, p: dict[str, Any]) -> None:
    plan.grasp_top("peg", plan.upright_yaw("peg") + math.pi, float(plan.scene.objects["peg"].pos[2]))
    plan.stand_upright("peg")
    plan.goal("upright", object="peg")
    plan.goal("released", object="peg")


@register_task("insert_side", backend="maniskill")
def insert_side(plan: Plan, p: dict[str, Any]) -> None:
    o = plan.scene.objects["peg"]
    half = o.dims["length"] / 2
    # Hold the peg's tail half (as ManiSkill's own solution does), the head free to enter the hole.
    plan.grasp_top("peg", yaw_of(o.body_quat), float(o.pos[2]), along=-max(0.05, half / 2 + 0.01), lift=0.10)
    plan.insert_side("peg", "hole")
    plan.goal("at", object="peg", xy="hole", tol=0.015)
    plan.goal("released", object="peg")


@register_task("insert_tube", backend="maniskill")
def insert_tube(plan: Plan, p: dict[str, Any]) -> None:
    hole = p.get("hole", "rack_hole1")
    _grasp(plan, "tube", {"grasp": "rod"})
    plan.insert_top("tube", hole)
    plan.goal("at", object="tube", xy=hole, tol=0.012)
    plan.goal("below", object="tube", z=0.04, what="bottom")


@register_task("press_button", backend="maniskill")
def press_button(plan: Plan, p: dict[str, Any]) -> None:
    plan.press("button")
    plan.goal_pressed("button")


@register_task("open_oven", backend="maniskill")
def open_oven(plan: Plan, p: dict[str, Any]) -> None:
    plan.door("oven", to_open=True)
    plan.goal_door("oven", to_open=True)


@register_task("close_oven", backend="maniskill")
def close_oven(plan: Plan, p: dict[str, Any]) -> None:
    plan.push_shut("oven")
    plan.goal_door("oven", to_open=False)


@register_task("shake", backend="maniskill")
def shake(plan: Plan, p: dict[str, Any]) -> None:
    q = _grasp(plan, "obj", p)
    o = plan.scene.objects["obj"]
    x, y, _ = o.pos
    plan.step("shake", object="obj")
    for i in range(3):
        plan.kf(f"left{i}", (x - 0.005, y - 0.05, 0.16), q, 1, "obj", speed=0.5)
        plan.kf(f"right{i}", (x - 0.005, y + 0.05, 0.16), q, 1, "obj", speed=0.5)
    plan.place("obj", "obj", q, returning=True, retreat=_retreat(p))
    plan.goal_placed("obj", "obj")


@register_task("place_and_press", backend="maniskill")
def place_and_press(plan: Plan, p: dict[str, Any]) -> None:
    """Put the vessel on the stirrer's plate, then press the start button."""
    q = _grasp(plan, "obj", p)
    plan.place("obj", "target", q, retreat=_retreat(p))
    plan.press("button")
    plan.goal_placed("obj", "target")
    plan.goal_pressed("button")
