"""Backend-neutral book-keeping of a keyframe plan: steps, keyframes and goals.

A backend's skills (grasp, place, press, ...) compute poses in its own terms and call these
primitives; what they record is what the labeler reads (`Step`, `Goal` of sim_backends/schema.py)
and what the stepping contract executes (`Keyframe`). Keyframe names are `s<step>_<name>`, the
names the perturbation specs in configs/tasks/*.yaml refer to.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

from sim_backends.schema import Goal, Step
from sim_backends.types import Keyframe

# m of cap travel that counts as pressed: the goal's threshold (labrobfail_vlm.actions.PRESS_TRAVEL is a push's length)
PRESSED_MIN_TRAVEL = 0.007


@dataclass
class PlanBuilder:
    DEFAULT_SPEED: ClassVar[float] = 0.4  # end-effector speed of a keyframe move (m/s) unless a skill says otherwise

    keyframes: list[Keyframe] = field(default_factory=list)
    steps: list[Step] = field(default_factory=list)
    goals: list[Goal] = field(default_factory=list)

    def step(self, action: str, **info: Any) -> None:
        """Open a new step (one atomic action); its keyframes follow."""
        self.steps.append(Step(len(self.steps), action, **info))

    def kf(self, name: str, pos, quat, gripper: int, target: str, speed: float | None = None, settle: int = 0) -> str:
        """Append a keyframe to the current step; returns its full name."""
        st, speed = self.steps[-1], self.DEFAULT_SPEED if speed is None else speed
        full = f"s{st.index}_{name}"
        self.keyframes.append(
            Keyframe(
                full,
                tuple(float(v) for v in pos),
                tuple(float(v) for v in quat),
                int(gripper),
                target,
                st.index,
                st.action,
                speed,
                settle,
            )
        )
        st.keyframes.append(full)
        return full

    def update(self, **info: Any) -> None:
        """Set what the labeler needs about the current step once its keyframes exist."""
        for k, v in info.items():
            setattr(self.steps[-1], k, v)

    def goal(self, kind: str, **kw: Any) -> None:
        self.goals.append(Goal(kind, dict(kw)))

    # The success conditions shared by both backends' templates, with their thresholds in one place.
    def goal_placed(self, obj: str, zone: str, tol: float = 0.04, released: bool = True) -> None:
        """`obj` stands upright within `tol` (m, horizontally) of `zone` (and, by default, out of the hand)."""
        self.goal("at", object=obj, xy=zone, tol=tol)
        self.goal("upright", object=obj)
        if released:
            self.goal("released", object=obj)

    def goal_pressed(self, button: str) -> None:
        self.goal("button", object=button, min_travel=PRESSED_MIN_TRAVEL)

    def goal_door(self, oven: str, to_open: bool) -> None:
        """Door angle (rad) at least 1.1 when opened, at most 0.12 when shut."""
        self.goal("door", object=oven, **({"min": 1.1} if to_open else {"max": 0.12}))

    def grip_offset(self, obj: str) -> list[float]:
        """End effector minus object position in the last grasp of `obj`."""
        return next(s.grip_offset for s in reversed(self.steps) if s.object == obj and s.grip_offset is not None)

    @property
    def actions(self) -> list[str]:
        return [s.action for s in self.steps]
