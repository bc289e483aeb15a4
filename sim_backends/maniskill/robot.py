"""The Panda keyframe controller on ManiSkill and the state read-outs the trace records.

No motion planner (ManiSkill's mplib segfaults with numpy 2): the arm runs ManiSkill's
`pd_joint_pos` controller, fed by a damped-least-squares inverse kinematics on SAPIEN's Pinocchio
model of the arm, with a null-space pull towards the Panda's rest posture and joint limits
respected (ManiSkill's own `pd_ee_pose` IK drifts along the arm's redundancy until a wrist joint
sits on its limit). A keyframe move interpolates the end-effector pose along a straight line
(position lerp, orientation slerp) at the keyframe's speed, one target per control step, then
converges on the keyframe and holds it for its settle time, like the PyBullet backend. When the
straight path leaves the arm's reach on the way (turning a held peg upright crosses between the
arm's posture families; a half turn of the hand may start the wrong way round into a joint limit),
the rest of the move goes in joint space to an IK solution of the keyframe seeded from the current
and the canonical postures; a skill that knows its move crosses families (turning a held peg
upright) asks for the joint-space move from the start.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from sim_backends.types import matrix_to_quat, quat_to_matrix, rotation_angle

ANG_SPEED = 0.8  # rad/s: orientation change per second during a move
REACHED = 0.002  # m: the keyframe counts as reached within this distance
AIM_LIMIT = 0.006  # m: the most the controller aims past a keyframe to cancel a steady tracking error
MAX_EXTRA = 12  # control steps allowed to converge on a keyframe after the interpolation
STALLED = 0.0005  # m: convergence stops after three control steps that gain less than this
IK_GIVE_UP = 0.01  # m + rad: IK error on the straight path beyond which the move goes in joint space
JOINT_SPEED = 1.0  # rad/s of the fastest joint in a joint-space move
REST = np.array([0.0, math.pi / 8, 0.0, -5 * math.pi / 8, 0.0, 3 * math.pi / 4, math.pi / 4])  # hand down
# Hand pointing forward: the arm stretched with the wrist pitched (far and high poses), or joint 5
# near +-2.6 (near and low poses, e.g. side grasps of glassware).
SIDE_RESTS = (
    np.array([0.0, 1.0, 0.0, -1.5, 0.0, 3.6, 0.785]),
    np.array([0.0, 0.3, 0.0, -2.6, 2.6, 1.8, 0.8]),
    np.array([0.0, 0.3, 0.0, -2.6, -2.6, 1.8, 0.8]),
)
IK_ITERS, IK_DAMP, IK_POSTURE, LIMIT_MARGIN = 30, 1e-3, 0.05, 0.02


def wxyz_to_xyzw(q) -> tuple[float, float, float, float]:
    return (float(q[1]), float(q[2]), float(q[3]), float(q[0]))


def slerp(q0, q1, a: float) -> tuple:
    q0, q1 = np.asarray(q0, float), np.asarray(q1, float)
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + a * (q1 - q0)
    else:
        th = math.acos(d)
        q = (math.sin((1 - a) * th) * q0 + math.sin(a * th) * q1) / math.sin(th)
    return tuple(q / np.linalg.norm(q))


def so3_log(r: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix (inverse of Rodrigues' formula)."""
    c = max(-1.0, min(1.0, (float(np.trace(r)) - 1.0) / 2.0))
    th = math.acos(c)
    v = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    if th < 1e-6:
        return 0.5 * v
    if th > math.pi - 1e-4:  # near pi the skew part vanishes: take the axis from the diagonal
        k = int(np.argmax(np.diag(r)))
        axis = r[:, k] + np.eye(3)[k]
        return th * axis / np.linalg.norm(axis)
    return th / (2.0 * math.sin(th)) * v


def canonical_quat(q_xyzw, frame: str) -> tuple:
    """The recorded orientation of an object (see envs.TaskObject.frame): for symmetric objects the
    frame whose z axis is the object's axis pointing up, so that `tilt` and rod ends read the same
    however the object lies."""
    if frame == "body":
        return tuple(float(v) for v in q_xyzw)
    r = quat_to_matrix(tuple(q_xyzw))
    if frame == "cube":
        k = int(np.argmax(np.abs(r[2, :])))
    elif frame == "x_axis":
        k = 0
    else:  # "rod": a rod along its body z axis
        k = 2
    z = r[:, k] * (1.0 if r[2, k] >= 0 else -1.0)
    x = r[:, (k + 1) % 3]
    return matrix_to_quat(np.stack([x, np.cross(z, x), z], axis=1))


class ArmIK:
    """Damped-least-squares IK of the TCP on the arm's Pinocchio model, with a rest-posture pull in
    the null space and joint limits; solved from the previous solution, so targets move smoothly."""

    def __init__(self, agent):
        robot = agent.robot
        self.pm = robot._objs[0].create_pinocchio_model()
        links = [lk.name for lk in robot._objs[0].links]
        self.link = links.index(agent.tcp._objs[0].name)
        self.n = len(robot._objs[0].active_joints)
        lim = robot.get_qlimits()[0].cpu().numpy()[:7]
        self.lo, self.hi = lim[:, 0] + LIMIT_MARGIN, lim[:, 1] - LIMIT_MARGIN

    def solve(
        self, q_full: np.ndarray, p_des: np.ndarray, r_des: np.ndarray, posture: np.ndarray, iters: int = IK_ITERS
    ) -> tuple[np.ndarray, float]:
        """Arm joint positions (7) that put the TCP at (p_des, r_des) in the robot's base frame, and the
        remaining error (metres + radians)."""
        q = np.array(q_full, float)
        for _ in range(iters):
            err = self._error(q, p_des, r_des)
            if np.linalg.norm(err[:3]) < 2e-4 and np.linalg.norm(err[3:]) < 2e-3:
                break
            j = self.pm.compute_single_link_local_jacobian(q, self.link)[:, :7]
            jj = j @ j.T + IK_DAMP * np.eye(6)
            dq = j.T @ np.linalg.solve(jj, err)
            null = np.eye(7) - j.T @ np.linalg.solve(jj, j)
            dq += null @ (IK_POSTURE * (posture - q[:7]))
            q[:7] = np.clip(q[:7] + dq, self.lo, self.hi)
        err = self._error(q, p_des, r_des)
        return q[:7], float(np.linalg.norm(err[:3]) + np.linalg.norm(err[3:]))

    def solve_far(self, q_full: np.ndarray, p_des: np.ndarray, r_des: np.ndarray) -> np.ndarray:
        """A solution for a distant pose: from the current and the canonical postures, the converged one
        nearest the current joint positions (the best one when none converges)."""
        cands = []
        for base in (q_full[:7], REST, *SIDE_RESTS):
            for turn in (0.0, -math.pi / 2, math.pi / 2, -math.pi):  # the hand's quarter turns
                seed = np.array(base, float)
                seed[6] = np.clip(seed[6] + turn, self.lo[6], self.hi[6])
                q0 = np.array(q_full, float)
                q0[:7] = seed
                q, e = self.solve(q0, p_des, r_des, seed, iters=200)
                cands.append((e > 5e-3, float(np.abs(q - q_full[:7]).sum()) if e <= 5e-3 else e, q))
        return min(cands, key=lambda c: (c[0], c[1]))[2]

    def _error(self, q: np.ndarray, p_des: np.ndarray, r_des: np.ndarray) -> np.ndarray:
        self.pm.compute_forward_kinematics(q)
        t = self.pm.get_link_pose(self.link).to_transformation_matrix()
        r_cur, p_cur = t[:3, :3], t[:3, 3]
        return np.concatenate([r_cur.T @ (p_des - p_cur), so3_log(r_cur.T @ r_des)])


class Arm:
    """Drives the Panda of a ManiSkill env to keyframes with `pd_joint_pos` + the gripper."""

    def __init__(self, env):
        self.env = env
        self.agent = env.agent
        self.dt = 1.0 / env.control_freq
        base = self.agent.robot.pose
        self.base_p = base.p[0].cpu().numpy().astype(float)
        self.base_r = quat_to_matrix(wxyz_to_xyzw(base.q[0].cpu().numpy()))
        self.ik = ArmIK(self.agent)
        self.q = self.agent.robot.get_qpos()[0].cpu().numpy().astype(float)  # the commanded joint positions
        self.posture = self.q[:7].copy()  # the null-space pull keeps the posture a move started in
        self.bias = np.zeros(3)  # aim offset that cancels the steady tracking error (see move_to)
        self.grip = 0
        self.target = self.tcp()

    def tcp(self) -> tuple[np.ndarray, tuple]:
        pose = self.agent.tcp.pose
        return pose.p[0].cpu().numpy().astype(float), wxyz_to_xyzw(pose.q[0].cpu().numpy())

    def width(self) -> float:
        q = self.agent.robot.get_qpos()[0].cpu().numpy()
        return float(q[-1] + q[-2])

    def _in_base(self, pos, quat) -> tuple[np.ndarray, np.ndarray]:
        return (self.base_r.T @ (np.asarray(pos, float) - self.base_p), self.base_r.T @ quat_to_matrix(tuple(quat)))

    def act(self, pos, quat, grip: int) -> bool:
        """One control step towards the end-effector pose (world frame) with the gripper command. An
        unreachable pose (IK error above IK_GIVE_UP) is not sent; returns whether it was."""
        q, err = self.ik.solve(self.q, *self._in_base(np.asarray(pos, float) + self.bias, quat), self.posture)
        if err > IK_GIVE_UP:
            return False
        self.target, self.grip = (np.asarray(pos, float), tuple(quat)), int(grip)
        self.q[:7] = q
        self._send()
        return True

    def _send(self) -> None:
        self.env.step(np.concatenate([self.q[:7], [-1.0 if self.grip else 1.0]]).astype(np.float32))

    def hold(self) -> None:
        self._send()

    def move_to(
        self,
        pos,
        quat,
        grip: int,
        speed: float,
        on_step: Callable[[], None],
        settle: int = 0,
        joint_space: bool = False,
    ) -> None:
        p0, q0 = self.target  # from the last commanded pose: the arm's own tracking lag does not compound
        pos = np.asarray(pos, float)
        dist = float(np.linalg.norm(pos - p0))
        ang = rotation_angle(q0, quat)
        self.posture = self.q[:7].copy()
        if int(grip) != self.grip:  # the load changes: the old offset no longer applies
            self.bias = np.zeros(3)
        if joint_space:  # the plan knows the straight path leaves the arm's reach (a turn between families)
            n = 0
            self._joint_move(pos, quat, grip, speed, on_step)
        else:
            n = max(2, math.ceil(max(dist / max(speed, 1e-3), ang / ANG_SPEED) / self.dt))
        for i in range(1, n + 1):
            a = i / n
            if not self.act(p0 + (pos - p0) * a, slerp(q0, quat, a), grip):
                self._joint_move(pos, quat, grip, speed, on_step)
                break
            on_step()
        # Converge, then hold for the settle time, aiming past the keyframe by the integrated remaining
        # offset (bounded), kept for the following moves: it cancels the steady error of the joint PD
        # under load (a held peg sags a few millimetres, more than an insertion's clearance).
        best, stalled = math.inf, 0
        for _ in range(MAX_EXTRA):
            cur, cq = self.tcp()
            err = float(np.linalg.norm(cur - pos))
            if err < REACHED and rotation_angle(cq, quat) < 0.05:
                break
            stalled = stalled + 1 if err > best - STALLED else 0
            if stalled >= 3:  # blocked or out of reach: waiting longer changes nothing
                break
            best = min(best, err)
            self._nudge(pos, cur, quat, grip)
            on_step()
        for _ in range(settle):
            self._nudge(pos, self.tcp()[0], quat, grip)
            on_step()

    def _joint_move(self, pos, quat, grip: int, speed: float, on_step: Callable[[], None]) -> None:
        """The rest of a move in joint space, from the commanded joint positions to a far IK solution."""
        self.bias = np.zeros(3)
        j0 = self.q[:7].copy()
        j1 = self.ik.solve_far(self.q, *self._in_base(pos, quat))
        cur = self.tcp()[0]
        n = max(
            2,
            math.ceil(
                max(
                    float(np.linalg.norm(np.asarray(pos) - cur)) / max(speed, 1e-3),
                    float(np.abs(j1 - j0).max()) / JOINT_SPEED,
                )
                / self.dt
            ),
        )
        self.target, self.grip = (np.asarray(pos, float), tuple(quat)), int(grip)
        for i in range(1, n + 1):
            self.q[:7] = j0 + (j1 - j0) * (i / n)
            self._send()
            on_step()
        self.posture = j1.copy()

    def _nudge(self, pos: np.ndarray, cur: np.ndarray, quat, grip: int) -> None:
        if np.linalg.norm(pos - cur) < AIM_LIMIT:  # farther off, the arm is still on its way: no windup
            self.bias = np.clip(self.bias + 0.5 * (pos - cur), -AIM_LIMIT, AIM_LIMIT)
        if not self.act(pos, quat, grip):  # out of reach: hold the last joint targets
            self.grip = int(grip)
            self._send()


class Contacts:
    """How many fingers of the Panda press on each task object (contact impulses of the last physics step,
    through ManiSkill's pairwise query, which serves the CPU and the GPU simulation alike)."""

    def __init__(self, env, bodies: dict[str, object]):
        self.scene = env.scene
        a = env.agent
        # not every Panda model has finger pads
        self.fingers = [
            [lk for lk in links if lk is not None]
            for links in ((a.finger1_link, a.finger1pad_link), (a.finger2_link, a.finger2pad_link))
        ]
        self.bodies = dict(bodies)

    def count(self) -> dict[str, int]:
        return {
            role: sum(any(self._touch(link, body) for link in links) for links in self.fingers)
            for role, body in self.bodies.items()
        }

    def _touch(self, link, body) -> bool:
        return float(np.linalg.norm(self.scene.get_pairwise_contact_impulses(link, body)[0].cpu().numpy())) > 1e-7
