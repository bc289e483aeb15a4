"""The PyBullet backend's recorder: the state trace sampled during an episode, and the checkpoints of prefix reuse."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Iterable

import pybullet as p

from sim_backends.pybullet import scene as scene_mod
from sim_backends.pybullet.robot import DT
from sim_backends.schema import MOVABLE

TRACE_EVERY = 6  # physics steps per trace sample: 240 Hz / 6 = 40 Hz
TRACE_RATE_HZ = round(1.0 / (DT * TRACE_EVERY), 6)  # recorded in every trace as `rate_hz`; the labeler reads it there


@dataclass
class Checkpoint:
    """A saved simulator state (PyBullet's saveState id) and the recorder's own state at that moment."""

    state: int
    steps: int
    cols: dict[str, list]
    kf_end: list[int]
    q_target: list[float]
    gripper_cmd: int
    grip_force: float


class Trace:
    """Samples the simulator state into columns (lists) at 40 Hz."""

    def __init__(self, scene: scene_mod.Scene):
        self.scene = scene
        self.cols: dict[str, list] = {"t": [], "kf": [], "ee_pos": [], "ee_quat": [], "width": [], "grip_cmd": []}
        self.kf_end: list[int] = []
        self.movables = {k: o for k, o in scene.objects.items() if o.kind in MOVABLE}
        self.vessels = {k: o for k, o in scene.objects.items() if o.kind == "vessel"}
        self.all_particles = [b for ids in scene.particles.values() for b in ids]

    def sample(self, t: float, kf: int) -> None:
        sc, cid, c = self.scene, self.scene.cid, self.cols
        r = lambda v: [round(float(x), 4) for x in v]  # noqa: E731
        pos, quat = sc.robot.ee_pose()
        c["t"].append(round(t, 4))
        c["kf"].append(kf)
        c["ee_pos"].append(r(pos))
        c["ee_quat"].append(r(quat))
        c["width"].append(round(sc.robot.finger_width(), 4))
        c["grip_cmd"].append(sc.robot.gripper_cmd)
        for name, o in self.movables.items():
            bp, bq = p.getBasePositionAndOrientation(o.body, physicsClientId=cid)
            c.setdefault(f"{name}.pos", []).append(r(bp))
            c.setdefault(f"{name}.quat", []).append(r(bq))
            c.setdefault(f"{name}.contacts", []).append(sc.robot.finger_contacts(o.body))
        for name, o in sc.objects.items():
            if o.kind in ("oven", "button"):
                c.setdefault(f"{name}.q", []).append(round(p.getJointState(o.body, 0, physicsClientId=cid)[0], 4))
        if self.all_particles:
            inside = {k: 0 for k in self.vessels}
            pts = [p.getBasePositionAndOrientation(b, physicsClientId=cid)[0] for b in self.all_particles]
            frames = {
                name: p.invertTransform(*p.getBasePositionAndOrientation(o.body, physicsClientId=cid))
                for name, o in self.vessels.items()
            }  # each vessel's world -> body transform, once
            free = 0
            for q in pts:
                hit = None
                for name, o in self.vessels.items():
                    inv = frames[name]
                    lp, _ = p.multiplyTransforms(inv[0], inv[1], q, (0, 0, 0, 1))
                    if math.hypot(lp[0], lp[1]) < o.dims["radius"] and -0.005 < lp[2] < o.dims["height"]:
                        hit = name
                        break
                if hit:
                    inside[hit] += 1
                else:
                    free += 1
            for k, v in inside.items():
                c.setdefault(f"liquid.{k}", []).append(v)
            c.setdefault("liquid.outside", []).append(free)

    def to_dict(self) -> dict[str, Any]:
        # Copies, so that a trace handed out mid-episode (supervision) does not grow under its reader.
        return {**{k: list(v) for k, v in self.cols.items()}, "kf_end": list(self.kf_end), "rate_hz": TRACE_RATE_HZ}


class Rewinder:
    """PyBulletSource's prefix-reuse hooks (sim_backends/prefix.py): a checkpoint is PyBullet's saved state plus the
    recorder's own; a rewind also unlights the lamps lit since (the next render lights what the rewound trace has
    pressed)."""

    cid: int
    scene: Any
    _trace: Trace
    _steps: int
    _lit: dict[int, list[tuple[int, tuple[float, ...]]]]
    _broken: set[str]
    _changed: bool

    def _checkpoint(self) -> Checkpoint:
        robot = self.scene.robot
        return Checkpoint(
            p.saveState(physicsClientId=self.cid),
            self._steps,
            {k: list(v) for k, v in self._trace.cols.items()},
            list(self._trace.kf_end),
            list(robot.q_target),
            robot.gripper_cmd,
            robot.grip_force,
        )

    def _rewind(self, cp: Checkpoint) -> None:
        p.restoreState(cp.state, physicsClientId=self.cid)
        self._steps = cp.steps
        self._trace.cols = {k: list(v) for k, v in cp.cols.items()}
        self._trace.kf_end = list(cp.kf_end)
        robot = self.scene.robot
        robot.q_target, robot.gripper_cmd, robot.grip_force = list(cp.q_target), cp.gripper_cmd, cp.grip_force
        for body, shapes in self._lit.items():  # unlit: the next render lights what the rewound trace has pressed
            for k, rgba in shapes:
                p.changeVisualShape(body, -1, shapeIndex=k, rgbaColor=rgba, physicsClientId=self.cid)
        self._lit = {}

    def _release(self, checkpoints: Iterable[Checkpoint]) -> None:
        if self.cid is not None and p.isConnected(self.cid):
            for cp in checkpoints:
                p.removeState(cp.state, physicsClientId=self.cid)

    def _world_clean(self) -> bool:
        # shards are bodies a saved state does not hold; a changed friction or mass is not in it either
        return not self._broken and not self._changed
