"""Franka Panda with a Cartesian keyframe controller (IK), gear-coupled fingers and a grip force."""

from __future__ import annotations

import functools
import hashlib
import math
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np
import pybullet as p
import pybullet_data

ARM_JOINTS = list(range(7))
FINGERS = (9, 10)
EE_LINK = 11  # the grasp target between the fingertips
SWEEP_LINKS = list(range(3, 12))  # from the elbow to the fingertips: the links that reach down to the bench
FINGER_OPEN = 0.04
REST = [0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.785]
LOWER = [-2.9, -1.76, -2.9, -3.07, -2.9, -0.02, -2.9]
UPPER = [2.9, 1.76, 2.9, -0.07, 2.9, 3.75, 2.9]
RANGES = [hi - lo for lo, hi in zip(LOWER, UPPER)]
DT = 1.0 / 240.0
TURN = 2.5  # rad/s: wrist rotation rate of a keyframe move
LIQUID_TURN = 0.8  # rad/s, while the closed gripper may hold liquid

# Orientation with the fingers pointing down and closing along the world y axis.
TOP_DOWN = p.getQuaternionFromEuler([math.pi, 0.0, 0.0])
# Fingers pointing along +x (horizontal approach), closing along the world y axis.
SIDE = p.getQuaternionFromEuler([math.pi / 2, math.pi / 2, math.pi / 2])


PANDA_DIR = Path(pybullet_data.getDataPath()) / "franka_panda"


@functools.lru_cache(maxsize=None)
def lowpoly_urdf() -> str:
    """The Panda URDF with its collision meshes (~3 k triangles) as visual meshes, written once per process.

    TinyRenderer is a software rasteriser whose cost is dominated by the ~130 k triangles of the
    stock visual meshes: 23 ms per 128 px image against 4.4 ms with these (measured, scripts/bench_sim.py).
    Physics is untouched (it always uses the collision meshes), so labels and trajectories are identical.
    One file per content in the temp folder, shared by every process (a folder per process had left one behind
    for each run), written atomically, so processes that start together never read half of it.
    """
    text = (PANDA_DIR / "panda.urdf").read_text()
    text = text.replace("package://meshes/visual/", f"{PANDA_DIR}/meshes/collision/")
    text = text.replace("package://", f"{PANDA_DIR}/")
    out = Path(tempfile.gettempdir()) / f"labrobfail_panda_{hashlib.sha256(text.encode()).hexdigest()[:16]}.urdf"
    if not out.is_file() or out.read_text() != text:
        from labrobfail_vlm.io import atomic_write_bytes

        atomic_write_bytes(out, text.encode())
    return str(out)


class Panda:
    def __init__(self, client: int, base=(0.0, 0.0, 0.0), grip_force: float = 60.0, lowpoly: bool = True):
        self.cid = client
        self.base = tuple(float(v) for v in base)  # where the base link stands (its URDF origin, not its mass centre)
        urdf = lowpoly_urdf() if lowpoly else str(PANDA_DIR / "panda.urdf")
        self.id = p.loadURDF(urdf, base, useFixedBase=True, physicsClientId=client)
        for j, q in zip(ARM_JOINTS, REST):
            p.resetJointState(self.id, j, q, physicsClientId=client)
        for f in FINGERS:
            p.resetJointState(self.id, f, FINGER_OPEN, physicsClientId=client)
            p.changeDynamics(
                self.id, f, lateralFriction=1.0, spinningFriction=0.001, frictionAnchor=True, physicsClientId=client
            )
        # Couple the fingers so that a grasp closes symmetrically (independent fingers push the object off-centre).
        c = p.createConstraint(
            self.id,
            FINGERS[0],
            self.id,
            FINGERS[1],
            p.JOINT_GEAR,
            [1, 0, 0],
            [0, 0, 0],
            [0, 0, 0],
            physicsClientId=client,
        )
        p.changeConstraint(c, gearRatio=-1, erp=0.1, maxForce=50, physicsClientId=client)
        self.grip_force = grip_force
        self.gripper_cmd = 0
        self.q_target = list(REST)
        self.carries_liquid = False  # scene.build sets it: liquid in play makes a closed gripper turn slowly

    # -- state ---------------------------------------------------------------------------------------
    def ee_pose(self) -> tuple[np.ndarray, tuple]:
        s = p.getLinkState(self.id, EE_LINK, computeForwardKinematics=True, physicsClientId=self.cid)
        return np.asarray(s[4]), tuple(s[5])

    def finger_width(self) -> float:
        return sum(p.getJointState(self.id, f, physicsClientId=self.cid)[0] for f in FINGERS)

    def finger_contacts(self, body: int) -> int:
        """Number of fingers touching `body` (one query: each point names the robot's link as its link A)."""
        links = {c[3] for c in p.getContactPoints(self.id, body, physicsClientId=self.cid)}
        return sum(1 for f in FINGERS if f in links)

    def sweep(self, poses, per_move: int = 6) -> np.ndarray:
        """Points (N x 3) that the links from the elbow to the fingertips pass through along a plan of (pos, quat)
        poses, moving in straight lines from the current pose: inverse kinematics chained as `move_to` chains it,
        no physics step. The joints are put back afterwards. Distractors keep clear of these (scene.py)."""
        q_keep, target_keep = (
            [p.getJointState(self.id, j, physicsClientId=self.cid)[0] for j in ARM_JOINTS],
            self.q_target,
        )
        cur, cur_q = self.ee_pose()
        out: list[tuple[float, float, float]] = []
        for pos, quat in poses:
            pos = np.asarray(pos, float)
            for i in range(1, per_move + 1):
                a = i / per_move
                q = self._ik(cur + (pos - cur) * a, p.getQuaternionSlerp(cur_q, quat, a))
                self.q_target = q
                for j, v in zip(ARM_JOINTS, q):
                    p.resetJointState(self.id, j, v, physicsClientId=self.cid)
                out.extend(
                    s[4]
                    for s in p.getLinkStates(
                        self.id, SWEEP_LINKS, computeForwardKinematics=True, physicsClientId=self.cid
                    )
                )
            cur, cur_q = pos, quat
        self.q_target = target_keep
        for j, v in zip(ARM_JOINTS, q_keep):
            p.resetJointState(self.id, j, v, physicsClientId=self.cid)
        return np.asarray(out, float).reshape(-1, 3)

    # -- commands ------------------------------------------------------------------------------------
    def set_gripper(self, closed: int) -> None:
        self.gripper_cmd = int(closed)
        target = 0.0 if closed else FINGER_OPEN
        for f in FINGERS:
            p.setJointMotorControl2(
                self.id, f, p.POSITION_CONTROL, target, force=self.grip_force, maxVelocity=0.2, physicsClientId=self.cid
            )

    def _ik(self, pos, quat) -> list[float]:
        q = p.calculateInverseKinematics(
            self.id,
            EE_LINK,
            pos,
            quat,
            LOWER,
            UPPER,
            RANGES,
            self.q_target,
            maxNumIterations=30,
            residualThreshold=1e-4,
            physicsClientId=self.cid,
        )
        return list(q[:7])

    def _drive_arm(self, q: list[float]) -> None:
        self.q_target = q
        p.setJointMotorControlArray(
            self.id,
            ARM_JOINTS,
            p.POSITION_CONTROL,
            targetPositions=q,
            forces=[200.0] * 7,
            positionGains=[0.3] * 7,
            physicsClientId=self.cid,
        )

    def move_to(
        self, pos, quat, speed: float, step: Callable[[], None], settle_steps: int = 0, max_extra: int = 60
    ) -> None:
        """Straight-line Cartesian move (position lerp, orientation slerp) at `speed` m/s, then settle."""
        p0, q0 = self.ee_pose()
        pos = np.asarray(pos, float)
        dist = float(np.linalg.norm(pos - p0))
        ang = 2 * math.acos(min(1.0, abs(float(np.dot(q0, quat)))))
        # A held vessel with liquid turns at <= 0.8 rad/s (faster rolls fling the liquid); otherwise the wrist
        # turns at 2.5 rad/s, which roughly halves the physics steps of a long task (scripts/bench_sim.py).
        turn = LIQUID_TURN if (self.gripper_cmd and self.carries_liquid) else TURN
        n = max(8, int(max(dist / speed, ang / turn) / DT))
        for i in range(1, n + 1):
            a = i / n
            if i % 4 == 1 or i == n:  # IK at 60 Hz is plenty for a 240 Hz position controller
                qi = p.getQuaternionSlerp(q0, quat, a)
                self._drive_arm(self._ik(p0 + (pos - p0) * a, qi))
            step()
        # Converge on the keyframe (bounded), then hold for the requested settle time.
        for _ in range(max_extra):
            cur, _ = self.ee_pose()
            if np.linalg.norm(cur - pos) < 0.004:
                break
            self._drive_arm(self._ik(pos, quat))
            step()
        for _ in range(settle_steps):
            step()
