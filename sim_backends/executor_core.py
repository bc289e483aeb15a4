"""Stepping and scene queries of the CorrectionExecutor (sim_backends/executor.py).

`ExecutorCore` holds what every primitive builds on: the state the correction starts from, stepping one keyframe
from the current state (commanded once more when it ends off target), and the lookups that turn a name, a
direction, a condition or a destination from the text into the scene's roles, vectors and positions (from the
backend's `task_meta()` and `scripted_keyframes()`). The primitives themselves are `CorrectionExecutor`'s.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Sequence

import numpy as np

from labrobfail_vlm.actions import DOOR_HANDLE, ORIGINAL, TARGET_POSITION, norm
from sim_backends.plan_builder import PRESSED_MIN_TRAVEL
from sim_backends.schema import MOVABLE, Step, TaskMeta
from sim_backends.source import FailureSource
from sim_backends.types import Keyframe, matrix_to_quat, quat_to_matrix, rotation_angle

SPEED = 0.3  # m/s of correction moves (the plan's skills use 0.2-0.45)
SLOW = 0.15  # final approaches, presses, door pulls
UNTIL_STEP = 0.02  # m per increment of a conditional move
MISS_POS, MISS_ROT = 0.01, 0.05  # m, rad: a move that ends further off than this is commanded again, once
TURN_SETTLE = 60  # physics steps after a turn in place: the controller converges on position, not orientation
RETREAT = 0.08  # m backed off along the approach axis before re-approaching an object
TRANSPORT_CLEARANCE = 0.10  # m above the higher of start and goal while carrying
AXES = {"x": np.array([1.0, 0, 0]), "y": np.array([0, 1.0, 0]), "z": np.array([0, 0, 1.0])}


class PrimitiveError(ValueError):
    """A primitive cannot run in this scene (unknown name, nothing to align to, no omitted step)."""


class ExecutorCore:
    """The state of a correction in progress, one-keyframe stepping and the scene lookups the primitives use."""

    def __init__(self, src: FailureSource):
        self.src = src

    # ---- state -------------------------------------------------------------------------------------------
    def _start(self, final: bool = False) -> None:
        self.final = final  # the policy has stopped (CorrectionExecutor.run)
        self.returns: dict[str, tuple[Step, bool]] = {}  # "omitted:<action>" -> the step it returns to, found once
        done = self.src.executed_so_far()
        self.nominal: list[Keyframe] = self.src.scripted_keyframes()
        self.meta: TaskMeta = self.src.task_meta(done)
        self.cur = done[-1] if done else self.nominal[0]  # name, step and action the correction runs under
        s = self._state()
        self.pos = np.asarray(s["ee_pos"], float)
        self.rot = quat_to_matrix(tuple(s["ee_quat"]))
        self.grip = int(s["grip_cmd"])
        self.count = 0
        self.note = ""
        self.step: int | None = None

    def _state(self) -> dict[str, Any]:
        return self.src.observe().state

    def _go(
        self,
        pos: Sequence[float],
        rot: np.ndarray | None = None,
        grip: int | None = None,
        speed: float = SPEED,
        settle: int = 0,
        kf: Keyframe | None = None,
    ) -> None:
        """Step one keyframe from the current state (as `kf`'s name and step when given)."""
        base = kf or self.cur
        self.pos = np.asarray(pos, float)
        self.rot = self.rot if rot is None else rot
        self.grip = self.grip if grip is None else int(grip)
        target = dataclasses.replace(
            base,
            pos=tuple(float(v) for v in self.pos),
            quat=matrix_to_quat(self.rot),
            gripper=self.grip,
            speed=speed,
            settle_steps=settle,
        )
        self.src.step(target)
        self.count += 1
        s = self._state()
        if (
            float(np.linalg.norm(np.asarray(s["ee_pos"]) - self.pos)) > MISS_POS
            or rotation_angle(tuple(s["ee_quat"]), target.quat) > MISS_ROT
        ):
            # the joint controller can end a move short or past (after a long hold the arm's null space
            # has drifted); closed loop, the executor commands the same target once more
            self.src.step(dataclasses.replace(target, speed=SLOW, settle_steps=max(settle, 30)))
            self.count += 1

    def _approach_axis(self) -> np.ndarray:
        return self.rot[:, 2]  # the gripper's z axis points along the fingers

    # ---- names -------------------------------------------------------------------------------------------
    def _role(self, name: str) -> str:
        """Scene role of a name from the text (its label, or the role itself)."""
        objs = self.meta.objects
        if name == DOOR_HANDLE:
            ovens = [r for r, o in objs.items() if o.kind == "oven"]
            if not ovens:
                raise PrimitiveError("the scene has no door")
            return self._step_object(ovens)
        if name in objs or name in self.meta.places:
            return name
        hits = [r for r, w in self.meta.labels.items() if norm(w) == norm(name)]
        if not hits:
            raise PrimitiveError(f"no object or place called {name!r} in this scene")
        return hits[0]

    def _step_object(self, roles: list[str]) -> str:
        """Of several candidate roles, the one the current step acts on (else the first)."""
        st = self.meta.steps[self.cur.segment] if self.cur.segment < len(self.meta.steps) else None
        return st.object if st is not None and st.object in roles else roles[0]

    def _steps(self, obj: str, action: str | None = None) -> list[Step]:
        return [s for s in self.meta.steps if s.object == obj and (action is None or s.action == action)]

    def _nominal(self, name: str) -> Keyframe:
        kf = next((k for k in self.nominal if k.name == name), None)
        if kf is None:
            raise PrimitiveError(f"the plan has no keyframe {name!r}")
        return kf

    def _held(self, obj: str) -> bool:
        s = self._state()
        return int(s.get(f"{obj}.contacts", 0)) > 0 and int(s["grip_cmd"]) == 1

    # ---- directions, conditions, destinations ------------------------------------------------------------
    def _direction(self, word: str) -> np.ndarray:
        a = self._approach_axis()
        table = {
            "forward": a,
            "backward": -a,
            "up": AXES["z"],
            "down": -AXES["z"],
            "left": AXES["y"],
            "right": -AXES["y"],
        }
        if word not in table:
            raise PrimitiveError(f"unknown direction {word!r}; expected one of {', '.join(table)}")
        return table[word]

    def _condition(self, until: str) -> Callable[[], bool]:
        goals = {g.kind: g.args for g in self.meta.goals}
        if until in ("door_open", "door_closed"):
            oven = self._role(DOOR_HANDLE)
            lo = float(goals.get("door", {}).get("min", 1.1)) if until == "door_open" else None
            hi = float(goals.get("door", {}).get("max", 0.12)) if until == "door_closed" else None
            return (
                lambda: (float(self._state()[f"{oven}.q"]) >= lo)
                if lo is not None
                else (float(self._state()[f"{oven}.q"]) <= hi)
            )
        if until == "pressed":
            buttons = [r for r, o in self.meta.objects.items() if o.kind == "button"]
            if not buttons:
                raise PrimitiveError("the scene has no button to press")
            b = self._step_object(buttons)
            travel = float(goals.get("button", {}).get("min_travel", PRESSED_MIN_TRAVEL))
            return lambda: float(self._state()[f"{b}.q"]) >= travel
        raise PrimitiveError(f"unknown condition {until!r}")

    def _held_object(self, obj: str | None) -> str:
        if obj is not None:
            return self._role(obj)
        s = self._state()
        held = [r for r, o in self.meta.objects.items() if o.kind in MOVABLE and s.get(f"{r}.contacts", 0)]
        if held:
            return held[0]
        st = self.meta.steps[self.cur.segment]
        if st.object in self.meta.objects and self.meta.objects[st.object].kind in MOVABLE:
            return st.object
        raise PrimitiveError("no object is held and none is named")

    def _destination(self, dest_id: str, obj: str) -> np.ndarray:
        if dest_id == ORIGINAL:
            return np.asarray(self.meta.objects[obj].home, float)
        if dest_id == TARGET_POSITION:
            places = [s for s in self._steps(obj, "place") if s.dest_xy is not None]
            if not places:
                raise PrimitiveError(f"the plan never places the {obj}")
            later = [s for s in places if s.index >= self.cur.segment] or places
            x, y = later[0].dest_xy
            return np.array([x, y, self.meta.bench_top])
        role = self._role(dest_id)
        if role in self.meta.places:
            return np.asarray(self.meta.places[role], float)
        return np.asarray(self.meta.objects[role].home, float)

    def _omitted_step(self, pose_id: str) -> tuple[Step, bool]:
        """The step "omitted:<action>" returns to, and whether it has run: the plan's first step with that action
        that was left out (it has not run, and lies before the current step unless the policy has stopped), else
        (a grasp) the grasp that did not take (`_grasp_not_taken`)."""
        action = pose_id.split(":", 1)[1]
        ran = set(self.meta.executed_steps())
        left_out = [s for s in self.meta.steps if s.index not in ran and (self.final or s.index < self.cur.segment)]
        step = next((s for s in left_out if s.action == action), None)
        if step is not None:
            return step, False
        missed = self._grasp_not_taken(ran) if action == "grasp" else None
        if missed is None:
            raise PrimitiveError(f"no {action} step was omitted")
        return missed, True

    def _grasp_not_taken(self, ran: set[int]) -> Step | None:
        """The grasp that ran but did not take: at this point the plan has its object in the hand (the keyframe the
        arm is in commands the fingers closed, in a step on that object) and the hand does not hold it (the fingers
        closed beside it, or it slipped out). To a person the grasp the plan needs here was never made, so "return
        to perform the omitted grasp" makes it. None where the plan holds nothing here, or the hand holds it."""
        kf = next((k for k in self.nominal if k.name == self.cur.name), None)
        if kf is None or kf.gripper != 1 or kf.segment >= len(self.meta.steps):
            return None
        obj = self.meta.steps[kf.segment].object
        if obj not in self.meta.objects or self.meta.objects[obj].kind not in MOVABLE or self._held(obj):
            return None
        grasps = [s for s in self._steps(obj, "grasp") if s.index in ran and s.index <= kf.segment]
        return grasps[-1] if grasps else None
