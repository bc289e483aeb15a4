"""Task templates: a keyframe program over named roles plus the goals that define success.

A scenario (configs/tasks/pybullet.yaml) = template x objects x layout. A new
scenario is a YAML entry; a new template is one function here.
"""

from __future__ import annotations

from typing import Any

from sim_backends.pybullet.plan import Plan
from sim_backends.registry import register_task


@register_task("pick", backend="pybullet")
def pick(plan: Plan, p: dict[str, Any]) -> None:
    """The atomic pick of the paper's short-horizon tasks (and of its recovery table): grasp, lift, hold."""
    plan.grasp("obj")
    plan.goal("held", object="obj")


@register_task("pick_place", backend="pybullet")
def pick_place(plan: Plan, p: dict[str, Any]) -> None:
    plan.grasp("obj")
    plan.place("obj", "target")
    plan.goal_placed("obj", "target")


@register_task("insert_tube", backend="pybullet")
def insert_tube(plan: Plan, p: dict[str, Any]) -> None:
    hole = p.get("hole", "rack_hole1")
    plan.grasp("tube")
    plan.insert("tube", hole)
    plan.goal("at", object="tube", xy=hole, tol=0.012)
    plan.goal("below", object="tube", z=0.06, what="bottom")


@register_task("press_button", backend="pybullet")
def press_button(plan: Plan, p: dict[str, Any]) -> None:
    plan.press("button")
    plan.goal_pressed("button")


@register_task("open_oven", backend="pybullet")
def open_oven(plan: Plan, p: dict[str, Any]) -> None:
    plan.door("oven", to_open=True)
    plan.goal_door("oven", to_open=True)


@register_task("close_oven", backend="pybullet")
def close_oven(plan: Plan, p: dict[str, Any]) -> None:
    plan.door("oven", to_open=False)
    plan.goal_door("oven", to_open=False)


@register_task("pour", backend="pybullet")
def pour(plan: Plan, p: dict[str, Any]) -> None:
    plan.grasp("src")
    plan.pour("src", "dest", side=float(p.get("side", -1.0)))
    plan.place("src", "src", returning=True)
    plan.goal("liquid", into="dest", min_fraction=0.5, source="src")
    plan.goal_placed("src", "src", released=False)


@register_task("stir", backend="pybullet")
def stir(plan: Plan, p: dict[str, Any]) -> None:
    plan.grasp("rod")
    plan.insert("rod", "vessel")
    plan.stir("rod", "vessel")
    plan.goal("stirred", object="rod", vessel="vessel", min_fraction=0.6)
    plan.goal("still", object="vessel", tol=0.03)
    plan.goal("held", object="rod")


@register_task("shake", backend="pybullet")
def shake(plan: Plan, p: dict[str, Any]) -> None:
    plan.grasp("obj")
    plan.shake("obj")
    plan.place("obj", "obj", returning=True)
    plan.goal_placed("obj", "obj")


@register_task("retrieve_from_oven", backend="pybullet")
def retrieve_from_oven(plan: Plan, p: dict[str, Any]) -> None:
    plan.door("oven", to_open=True)
    plan.grasp("obj", inside=True)
    plan.place("obj", "target")
    plan.door("oven", to_open=False)
    plan.goal_placed("obj", "target", released=False)
    plan.goal_door("oven", to_open=False)


@register_task("load_oven", backend="pybullet")
def load_oven(plan: Plan, p: dict[str, Any]) -> None:
    plan.door("oven", to_open=True)
    plan.grasp("obj")
    plan.place("obj", "inside", inside=True)
    plan.door("oven", to_open=False)
    plan.goal_placed("obj", "inside", released=False)
    plan.goal_door("oven", to_open=False)


@register_task("pour_and_stir", backend="pybullet")
def pour_and_stir(plan: Plan, p: dict[str, Any]) -> None:
    plan.grasp("src")
    plan.pour("src", "dest", side=float(p.get("side", -1.0)))
    plan.place("src", "src", returning=True)
    plan.grasp("rod")
    plan.insert("rod", "dest")
    plan.stir("rod", "dest")
    plan.goal("liquid", into="dest", min_fraction=0.5, source="src")
    plan.goal("at", object="src", xy="src", tol=0.04)
    plan.goal("stirred", object="rod", vessel="dest", min_fraction=0.6)
    plan.goal("held", object="rod")


def _then_start(plan: Plan) -> None:
    """Finish an oven workflow by pressing the button that starts the drying cycle."""
    plan.home()
    plan.press("button")
    plan.goal_pressed("button")


@register_task("retrieve_and_start", backend="pybullet")
def retrieve_and_start(plan: Plan, p: dict[str, Any]) -> None:
    """Fetch a sample from the oven, close it and start the next drying cycle."""
    retrieve_from_oven(plan, p)
    _then_start(plan)


@register_task("load_and_start", backend="pybullet")
def load_and_start(plan: Plan, p: dict[str, Any]) -> None:
    load_oven(plan, p)
    _then_start(plan)
