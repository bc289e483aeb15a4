"""CorrectionExecutor: runs Action Dictionary primitives (labrobfail_vlm/actions.py) in a backend.

It drives the backend only through the `FailureSource` stepping contract: every primitive reads the
current state (`observe()`), turns into one or more keyframes relative to it and `step`s them, from
wherever the arm is (never a reset). What a primitive needs to know about the task (where an object is
grasped, where the plan puts it, how the plan pours, which keyframes a skipped step has) comes from the
backend's public `task_meta()` and `scripted_keyframes()`, so the executor is backend-agnostic.

Correction keyframes carry the name, step and action of the keyframe the arm was executing (the labeler's
program counter stays in the step being corrected); `move_to_pose` replays the plan's own keyframes under
their own names. A correction with a `manual` phrase is not run at all (a person must act).

Primitive semantics (frames as documented in labrobfail_vlm/actions.py):
  hold_position      hold still for a moment             delta_pos        move along a direction; `until` =
  oscillate          n strokes of +-amp along an axis                        door_open/door_closed/pressed stops
  align_to           back off, go to the object's grasp pre-pose, then its     in 2 cm increments once the state
                     grasp point (a device: the plan's approach keyframes)      says so (a door is followed: the
  move_above         grasp first if not held, lift, carry the held object       gripper turns with its angle)
                     above the destination, lower to h above its surface
  align_above        the plan's pouring pose for src over dest (its last keyframe before the tilt)
  move_to_pose       the keyframes of the omitted step (pose_id "omitted:<action>"; its object grasped first when
                     the step carries it) or one named keyframe; "omitted:grasp" where no grasp was skipped but
                     the plan has an object in the hand that the hand does not hold: that grasp made again
  set_orient         level the gripper: the step's planned orientation with the current heading (yaw)
  hold_orientation / hold_gripper   keep what is there (no motion)
  rotate             turn about a world axis;  tilt_pour  roll as the plan pours, in three stages, then upright
  gripper_open / gripper_close      command the fingers and let them settle
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from labrobfail_vlm.actions import DOOR_HANDLE, MANUAL, PRIMITIVES
from sim_backends.executor_core import (  # the constants and PrimitiveError stay importable from here
    AXES,
    MISS_POS,  # noqa: F401
    MISS_ROT,  # noqa: F401
    RETREAT,
    SLOW,
    SPEED,
    TRANSPORT_CLEARANCE,
    TURN_SETTLE,
    UNTIL_STEP,
    ExecutorCore,
    PrimitiveError,
)
from sim_backends.perturbations.control import so3_exp
from sim_backends.schema import MOVABLE
from sim_backends.types import quat_to_matrix, rotation_angle


@dataclass
class ExecResult:
    executed: bool  # every primitive ran
    keyframes: int = 0  # keyframes stepped
    manual: list[str] = field(default_factory=list)  # phrases a person must handle (nothing was run)
    error: str | None = None  # the primitive that could not run, and why
    log: list[dict[str, Any]] = field(default_factory=list)  # per primitive: op, args, keyframes, note
    # the plan step a primitive redid last (a grasp, a device approach, a replayed keyframe): where the arm stands
    # near two keyframes of the plan (a pour sets the vessel back where it grasped it), the policy's re-planning
    # goes on in this step (`resume_index`)
    step: int | None = None

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _rz(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def yaw_aligned(ref: np.ndarray, cur: np.ndarray) -> np.ndarray:
    """Rz(psi) @ ref for the heading psi that brings it closest to `cur` (argmax of trace(cur^T Rz ref))."""
    m = ref @ cur.T
    return _rz(math.atan2(m[0, 1] - m[1, 0], m[0, 0] + m[1, 1])) @ ref


def _axis_angle(r: np.ndarray) -> np.ndarray:
    """so(3) vector of a rotation matrix (inverse of so3_exp)."""
    ang = math.acos(max(-1.0, min(1.0, (float(np.trace(r)) - 1) / 2)))
    if ang < 1e-9:
        return np.zeros(3)
    v = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    n = float(np.linalg.norm(v))
    if n < 1e-9:  # ~pi: the axis is the dominant column of R + I
        w = r + np.eye(3)
        v = w[:, int(np.argmax(np.linalg.norm(w, axis=0)))]
        n = float(np.linalg.norm(v))
    return v / n * ang


class CorrectionExecutor(ExecutorCore):
    """Runs Action Dictionary primitives: `run` and the primitives (`_<op>`); stepping and scene queries are
    `ExecutorCore`'s (sim_backends/executor_core.py)."""

    # ---- entry point -------------------------------------------------------------------------------------
    def run(self, primitives: Sequence[dict[str, Any]], final: bool = False) -> ExecResult:
        """Execute `primitives` in order from the current state; stops at the first one that cannot run. `final`:
        the policy has stopped, so a step of the plan that never ran was left out even when no later step ran (a
        last step skipped); while it runs, only a step before the current one was omitted (a later one is to come)."""
        manual = [str(p["args"].get("phrase", "")) for p in primitives if p.get("op") == MANUAL]
        if manual:
            return ExecResult(False, manual=manual, error="manual correction: not executed")
        unknown = [str(p.get("op")) for p in primitives if p.get("op") not in PRIMITIVES]
        if unknown:
            return ExecResult(False, error=f"unknown primitive {unknown[0]!r}")
        self._start(final)
        # a plan that names an omitted step that is not there cannot do what it says: refuse it before its first
        # primitive moves the arm (a pause before an impossible return would disturb a policy that was on course);
        # the step found here is the one the return runs, whatever the primitives before it change
        for p in primitives:
            pose_id = str(p.get("args", {}).get("pose_id", ""))
            if p.get("op") == "move_to_pose" and pose_id.startswith("omitted:"):
                try:
                    self.returns[pose_id] = self._omitted_step(pose_id)
                except PrimitiveError as e:
                    return ExecResult(False, error=f"move_to_pose: {e}")
        res = ExecResult(True)
        for p in primitives:
            n0 = self.count
            self.note = ""
            try:
                getattr(self, f"_{p['op']}")(**p.get("args", {}))
            except PrimitiveError as e:
                res.executed, res.error = False, f"{p['op']}: {e}"
            except TypeError as e:  # wrong argument names from a hand-written primitive list
                res.executed, res.error = False, f"{p['op']}: bad arguments ({e})"
            res.log.append(
                {
                    "op": p["op"],
                    "args": dict(p.get("args", {})),
                    "keyframes": self.count - n0,
                    **({"note": self.note} if self.note else {}),
                }
            )
            if not res.executed:
                break
        res.keyframes, res.step = self.count, self.step
        return res

    # ---- position primitives -----------------------------------------------------------------------------
    def _hold_position(self) -> None:
        self._go(self.pos, settle=24)

    def _delta_pos(self, direction: str, dist: float, until: str | None = None, into: str | None = None) -> None:
        if until is None:
            self._go(self.pos + self._direction(direction) * float(dist), speed=SLOW)
            return
        done = self._condition(until)
        device = self._role(DOOR_HANDLE) if until.startswith("door") else None
        if device and not done():
            self._follow_door(device, done)
        q0 = float(self._state()[f"{device}.q"]) if device else 0.0
        rot0 = self.rot
        for _ in range(max(1, int(math.ceil(float(dist) / UNTIL_STEP)))):
            if done():
                break
            if device:  # the handle swings about the hinge: turn the gripper with the door
                self.rot = _rz(float(self._state()[f"{device}.q"]) - q0) @ rot0
            ee = np.asarray(self._state()["ee_pos"], float)
            self._go(ee + self._direction(direction) * UNTIL_STEP, speed=SLOW)
        self.note = "condition met" if done() else f"stopped after {dist} m: {until} not reached"

    def _follow_door(self, oven: str, done: Callable[[], bool]) -> None:
        """A held door handle moves on the hinge's arc, not a line: pull it through the plan's arc keyframes
        (the door step's closed-gripper keyframes after the grip) from the door's current angle on."""
        st = next((s for s in self._steps(oven) if s.contact_kf and s.target_angle is not None), None)
        if st is None:
            return
        names = st.keyframes[st.keyframes.index(st.contact_kf) + 1 :]
        arc = []
        for n in names:
            k = self._nominal(n)
            if not k.gripper:
                break
            arc.append(k)
        a0 = float(self.src.trace_so_far()[f"{oven}.q"][0])
        span = float(st.target_angle) - a0
        if not arc or abs(span) < 1e-3:
            return
        done_frac = (float(self._state()[f"{oven}.q"]) - a0) / span
        for i, k in enumerate(arc):
            if (i + 1) / len(arc) <= done_frac + 0.02:
                continue  # the door is past this keyframe already
            if done():
                return
            self._go(k.pos, quat_to_matrix(k.quat), grip=1, speed=SLOW)

    def _oscillate(self, axis: str, amp: float, n: int) -> None:
        if axis not in AXES:
            raise PrimitiveError(f"unknown axis {axis!r}")
        c = self.pos.copy()
        for _ in range(int(n)):
            self._go(c - AXES[axis] * float(amp), speed=0.1)
            self._go(c + AXES[axis] * float(amp), speed=0.1)
        self._go(c, speed=0.1)

    def _align_to(self, target_id: str, stage: str | None = None) -> None:
        role = self._role(target_id)
        kind = self.meta.objects[role].kind if role in self.meta.objects else "zone"
        if kind in ("oven", "button"):
            self._align_device(role, stage)
            return
        if kind not in MOVABLE:
            raise PrimitiveError(f"cannot centre the gripper on {target_id!r} (a {kind})")
        if self._held(role):
            self.note = "already held"
            return
        grasp = next((s for s in self._steps(role, "grasp") if s.grip_offset is not None), None)
        if grasp is None:
            raise PrimitiveError(f"the plan never grasps {target_id!r}")
        pre, reach = (self._nominal(n) for n in grasp.keyframes[:2])
        axis = np.asarray(reach.pos) - np.asarray(pre.pos)
        span = float(np.linalg.norm(axis))
        axis = axis / span
        goal = np.asarray(self._state()[f"{role}.pos"], float) + np.asarray(grasp.grip_offset)
        rot = quat_to_matrix(reach.quat)
        if float(np.linalg.norm(self.pos - goal)) < span + 0.05:  # near the object: back off first
            self._go(self.pos - self._approach_axis() * RETREAT + AXES["z"] * 0.01)
        self._go(goal - axis * span, rot)
        if stage != "pre":
            self._go(goal, rot, speed=SLOW, settle=10)
        self.step = grasp.index

    def _align_device(self, role: str, stage: str | None) -> None:
        """The plan's approach to a handle or button: its step's keyframes before the contact keyframe."""
        st = next((s for s in self._steps(role) if s.contact_kf), None)
        if st is None:
            raise PrimitiveError(f"the plan never operates the {role}")
        names = st.keyframes[: st.keyframes.index(st.contact_kf)]
        if stage == "pre":
            names = names[:-1]
        if float(np.linalg.norm(self.pos - np.asarray(self._nominal(names[-1]).pos))) > 0.02:
            self._go(self.pos - self._approach_axis() * RETREAT)  # off the handle before going round
        for n in names:
            k = self._nominal(n)
            self._go(k.pos, quat_to_matrix(k.quat), grip=k.gripper, speed=min(k.speed, SPEED))
        self.step = st.index

    def _ensure_held(self, obj: str) -> None:
        """Carrying primitives need the object in the hand: grasp it first when it is not. A fixed device (the oven,
        the button: a model's correction can name one) cannot be carried, and is refused before anything moves."""
        kind = self.meta.objects[obj].kind if obj in self.meta.objects else "zone"
        if kind not in MOVABLE:
            raise PrimitiveError(f"cannot carry {obj!r}: {'a place' if kind == 'zone' else f'the {kind} is fixed'}")
        if self._held(obj):
            return
        self._gripper_open()
        self._align_to(obj)
        self._gripper_close()
        self.note = "grasped first"

    def _carry(self, goal: np.ndarray, rot: np.ndarray | None = None) -> None:
        """Lift, travel at a clearance above start and goal, then lower onto `goal`."""
        z = max(float(self.pos[2]), float(goal[2])) + TRANSPORT_CLEARANCE
        self._go([self.pos[0], self.pos[1], z])
        self._go([goal[0], goal[1], z], rot)
        self._go(goal, speed=SLOW)

    def _move_above(self, dest_id: str, h: float, obj: str | None = None) -> None:
        role = self._held_object(obj)
        self._ensure_held(role)
        s = self._state()
        offset = np.asarray(s["ee_pos"], float) - np.asarray(s[f"{role}.pos"], float)
        d = self._destination(dest_id, role)
        self._carry(np.array([d[0] + offset[0], d[1] + offset[1], d[2] + offset[2] + float(h) + 0.004]))

    def _align_above(self, src: str, dest: str) -> None:
        role, dst = self._role(src), self._role(dest)
        self._ensure_held(role)
        pours = [s for s in self._steps(role, "pour") if s.dest == dst] or self._steps(role, "pour")
        if pours:  # the plan's pouring pose: its last keyframe before the vessel starts to tilt
            ks = [self._nominal(n) for n in pours[0].keyframes]
            level = [k for k in ks if rotation_angle(k.quat, ks[0].quat) < 0.05]
            k = next((a for a, b in zip(ks, ks[1:]) if rotation_angle(b.quat, ks[0].quat) >= 0.05), level[-1])
            self._carry(np.asarray(k.pos, float), quat_to_matrix(k.quat))
            return
        home = np.asarray(self.meta.objects[dst].home, float)
        height = float(self.meta.objects[dst].dims.get("height", 0.1))
        self._carry(home + np.array([0.0, 0.0, height + 0.12]))
        self.note = "no pour in the plan: straight above the destination"

    def _move_to_pose(self, pose_id: str) -> None:
        if pose_id.startswith("omitted:"):
            step, redo = self.returns[pose_id]  # found by run's check before the first primitive moved
            if redo:  # a grasp that did not take: made again where the object now stands, as align_to makes one
                n0 = self.count
                self._ensure_held(step.object)
                self.step = step.index
                self.note = "the grasp that did not take, made again" if self.count > n0 else "already held"
                return
            kfs = [k for k in self.nominal if k.segment == step.index]
            # a step the plan enters holding its object (a pour, a place) needs it in the hand: a vessel set down
            # unpoured is picked up again first, as move_above and align_above do
            carried = self.meta.objects.get(step.object)
            if kfs and kfs[0].gripper == 1 and carried is not None and carried.kind in MOVABLE:
                self._ensure_held(step.object)
            for kf in kfs:
                self._go(
                    kf.pos, quat_to_matrix(kf.quat), grip=kf.gripper, speed=kf.speed, settle=kf.settle_steps, kf=kf
                )
            self.cur = self.src.executed_so_far()[-1]
            self.step = step.index
            return
        kf = self._nominal(pose_id)
        self._go(kf.pos, quat_to_matrix(kf.quat), grip=kf.gripper, speed=kf.speed, settle=kf.settle_steps, kf=kf)
        self.step = kf.segment

    # ---- orientation primitives --------------------------------------------------------------------------
    def _set_orient(self, roll: float = 0.0, pitch: float = 0.0) -> None:
        st = self.meta.steps[self.cur.segment] if self.cur.segment < len(self.meta.steps) else None
        first = self._nominal(st.keyframes[0]) if st is not None and st.keyframes else self.nominal[0]
        rot = yaw_aligned(quat_to_matrix(first.quat), self.rot)
        rot = so3_exp(AXES["y"] * float(pitch)) @ so3_exp(AXES["x"] * float(roll)) @ rot
        self._go(self.pos, rot, speed=SLOW, settle=TURN_SETTLE)

    def _hold_orientation(self) -> None:
        self.note = "orientation kept"

    def _rotate(self, axis: str, angle: float) -> None:
        if axis not in AXES:
            raise PrimitiveError(f"unknown axis {axis!r}")
        self._go(self.pos, so3_exp(AXES[axis] * float(angle)) @ self.rot, speed=SLOW, settle=TURN_SETTLE)

    def _tilt_pour(self, angle: float, v: float) -> None:
        """Roll the held vessel the way the plan pours (its axis and sense, in the gripper frame), in three
        stages that let the liquid run, then back upright. `v` is bounded by the controller's 0.8 rad/s."""
        pours = [s for s in self.meta.steps if s.action == "pour"]
        axis = np.array([0.0, 0.0, -1.0])  # about the approach axis, by default
        if pours:
            ks = [self._nominal(n) for n in pours[0].keyframes]
            r0 = quat_to_matrix(ks[0].quat)
            rel = [_axis_angle(r0.T @ quat_to_matrix(k.quat)) for k in ks]
            big = max(rel, key=lambda w: float(np.linalg.norm(w)))
            if float(np.linalg.norm(big)) > 1e-3:
                axis = big / float(np.linalg.norm(big))
        start, upright = self.pos.copy(), self.rot
        for frac in (0.45, 0.75, 1.0):
            self._go(start, upright @ so3_exp(axis * float(angle) * frac), speed=0.2, settle=40)
        self._go(start + AXES["z"] * 0.04, upright, speed=0.3)

    # ---- gripper primitives ------------------------------------------------------------------------------
    def _hold_gripper(self) -> None:
        self.note = "gripper kept " + ("closed" if self.grip else "open")

    def _gripper_open(self) -> None:
        self._go(self.pos, grip=0, settle=40)

    def _gripper_close(self) -> None:
        self._go(self.pos, grip=1, settle=50)
