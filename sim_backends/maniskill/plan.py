"""Keyframe skills of the ManiSkill backend (grasp, place, push, stand upright, insert, door, press).

Poses are in ManiSkill's world frame (table top z = 0, Panda base at x = -0.615), orientations of
the Panda's TCP (z = approach, y = finger closing direction) as (x, y, z, w) quaternions. Skills
read the initial scene (`SceneView`) and write steps, keyframes and goals through `PlanBuilder`;
nothing here touches the simulator, so a plan is a pure function of the initial state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from sim_backends.maniskill import assets
from sim_backends.plan_builder import PlanBuilder
from sim_backends.types import matrix_to_quat, quat_to_matrix

SAFE_Z = 0.20  # carry height of the end effector


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def top_down(yaw: float = 0.0) -> tuple:
    """Fingers pointing down; yaw 0 closes them along the world y axis."""
    return matrix_to_quat(rot_z(yaw) @ rot_x(math.pi))


def side(yaw: float = 0.0) -> tuple:
    """Fingers pointing horizontally (along +x at yaw 0), closing along the world y axis."""
    return matrix_to_quat(rot_z(yaw) @ rot_y(math.pi / 2))


def yaw_of(quat_xyzw) -> float:
    m = quat_to_matrix(tuple(quat_xyzw))
    return math.atan2(m[1, 0], m[0, 0])


def wrap(a: float, period: float) -> float:
    """`a` shifted by whole periods into [-period/2, period/2)."""
    return (a + period / 2) % period - period / 2


@dataclass
class Thing:
    kind: str
    pos: np.ndarray  # position as recorded in the trace (see envs.TaskObject.frame)
    dims: dict[str, float]
    body_quat: tuple = (0.0, 0.0, 0.0, 1.0)  # the body's own orientation (x, y, z, w)


@dataclass
class SceneView:
    """The initial state a plan is computed from."""

    objects: dict[str, Thing]
    zones: dict[str, tuple[float, float, float]]
    extra: dict[str, object] = field(default_factory=dict)  # task-specific poses (e.g. the peg's goal)


class Plan(PlanBuilder):
    def __init__(self, scene: SceneView):
        super().__init__()
        self.scene = scene
        self.joint_space: set[str] = set()  # keyframes the controller reaches in joint space (robot.Arm)

    def _where(self, name: str) -> np.ndarray:
        if name in self.scene.zones:
            return np.asarray(self.scene.zones[name], float)
        return np.asarray(self.scene.objects[name].pos, float)

    # -- grasps ---------------------------------------------------------------------------------------
    def grasp_top(self, obj: str, yaw: float, z: float, along: float = 0.0, lift: float = 0.12) -> None:
        """Top-down grasp at height `z`, `along` metres from the centre along the object's x axis.

        A hand yaw beyond +-pi/2 of the rest pose is first turned to halfway, so that the hand turns
        the way round that keeps the last joint inside its limits (slerp alone may start either way)."""
        o = self.scene.objects[obj]
        q = top_down(yaw)
        ax = quat_to_matrix(o.body_quat)[:, 0]
        x, y = o.pos[:2] + along * ax[:2]
        self.step("grasp", object=obj)
        if abs(wrap(yaw, 2 * math.pi)) > math.pi / 2 + 0.1:
            self.kf("orient", (x, y, z + 0.14), top_down(wrap(yaw, 2 * math.pi) / 2), 0, obj)
        self.kf("pre", (x, y, z + 0.10), q, 0, obj)
        self.kf("reach", (x, y, z), q, 0, obj, speed=0.25)
        close = self.kf("close", (x, y, z), q, 1, obj, settle=8)
        self.kf("lift", (x, y, z + lift), q, 1, obj, speed=0.3)
        width = 2 * o.dims.get("radius", 0.02)
        self.update(
            close_kf=close, grip_offset=[float(x - o.pos[0]), float(y - o.pos[1]), float(z - o.pos[2])], width=width
        )

    def grasp_cube(self, obj: str) -> None:
        o = self.scene.objects[obj]
        yaw = wrap(yaw_of(o.body_quat), math.pi / 2)  # a cube's faces repeat every 90 degrees
        self.grasp_top(obj, yaw, float(o.pos[2]))

    def grasp_side(self, obj: str) -> None:
        """Side grasp of a vessel, approaching along +x (the robot stands at -x)."""
        o = self.scene.objects[obj]
        x, y, z = o.pos
        zg = z + min(0.6 * o.dims["height"], 0.05)
        self.step("grasp", object=obj)
        self.kf("pre", (x - 0.13, y, zg), side(), 0, obj)
        self.kf("reach", (x - 0.005, y, zg), side(), 0, obj, speed=0.25)
        close = self.kf("close", (x - 0.005, y, zg), side(), 1, obj, settle=8)
        self.kf("lift", (x - 0.005, y, zg + 0.12), side(), 1, obj, speed=0.3)
        self.update(close_kf=close, grip_offset=[-0.005, 0.0, float(zg - z)], width=2 * o.dims["radius"])

    # -- placing --------------------------------------------------------------------------------------
    def place(
        self, obj: str, dest: str, quat, surface: float = 0.0, returning: bool = False, retreat=(0.0, 0.0, 0.10)
    ) -> None:
        """Carry the held object over `dest`, lower it onto a surface at height `surface`, release, retreat."""
        g = self.grip_offset(obj)
        dx, dy = self._where(dest)[:2]
        home_z = self.scene.objects[obj].pos[2]  # the held point's height above the surface it stood on
        zr = surface + home_z + g[2] + 0.004
        x, y = dx + g[0], dy + g[1]
        self.step("place", object=obj, dest=dest, dest_xy=[float(dx), float(dy)], returning=returning)
        self.kf("carry", (x, y, max(zr + 0.10, SAFE_Z)), quat, 1, dest)
        self.kf("lower", (x, y, zr), quat, 1, dest, speed=0.2)
        # A release lasts about 0.2 s (2 interpolation + 2 settle steps): the labeler's slip check ends
        # 0.2 s before it ends (labeler.RELEASE_LEAD), so a longer release would read the opening
        # fingers as a slip.
        rel = self.kf("release", (x, y, zr), quat, 0, dest, settle=2)
        self.kf("retreat", (x + retreat[0], y + retreat[1], zr + retreat[2]), quat, 0, dest, speed=0.3)
        self.update(release_kf=rel)

    def push(self, obj: str, dest: str) -> None:
        """Slide an object over the table to `dest` with the closed fingers (a non-prehensile place)."""
        o = self.scene.objects[obj]
        half = o.dims["height"] / 2
        start, goal = o.pos[:2], self._where(dest)[:2]
        u = (goal - start) / max(1e-6, float(np.linalg.norm(goal - start)))
        back = half + 0.03  # where the fingers start, behind the object
        q = top_down(wrap(math.atan2(u[1], u[0]) + math.pi / 2, math.pi))  # finger faces towards the motion
        a = start - back * u
        b = goal - (half + 0.012) * u  # the fingers' front face stops where the object's centre is on target
        z = half + 0.002
        self.step("place", object=obj, dest=dest, dest_xy=[float(goal[0]), float(goal[1])], returning=False)
        self.kf("above", (a[0], a[1], z + 0.10), q, 1, dest)
        self.kf("down", (a[0], a[1], z), q, 1, dest, speed=0.2)
        end = self.kf("push", (b[0], b[1], z), q, 1, dest, speed=0.12, settle=4)
        self.kf("retreat", (b[0] - 0.03 * u[0], b[1] - 0.03 * u[1], z + 0.10), q, 1, dest, speed=0.3)
        self.update(release_kf=end)

    def upright_yaw(self, obj: str) -> float:
        """Yaw of the side pose (`side(yaw)`) that holds a lying peg upright: fingers across the peg,
        pointing away from the robot. Grasp it top-down at yaw + pi, then turn about the fingers."""
        return wrap(yaw_of(self.scene.objects[obj].body_quat), math.pi)

    def stand_upright(self, obj: str) -> None:
        """A peg held top-down across its centre: lift, turn it about the finger axis until it is
        vertical, set it down on its end, release and back off (a place onto its own spot)."""
        o = self.scene.objects[obj]
        g = self.grip_offset(obj)
        half = o.dims["length"] / 2
        hold = self.keyframes[-1]
        a = self.upright_yaw(obj)
        q1 = side(a)
        x, y = o.pos[0] + g[0], o.pos[1] + g[1]
        zc = half + 0.006  # the peg's centre when it stands on its end
        self.step("place", object=obj, dest=obj, dest_xy=[float(o.pos[0]), float(o.pos[1])], returning=False)
        # Turn low: the Panda reaches a forward-pointing hand poorly above ~0.2 m this close to its base.
        self.kf("raise", (x, y, half + 0.05), hold.quat, 1, obj, speed=0.3)
        # From a hand pointing down to one pointing forward the arm changes posture family: no straight
        # Cartesian path stays within its joint limits.
        self.joint_space.add(self.kf("turn", (x, y, half + 0.05), q1, 1, obj, speed=0.3, settle=4))
        self.kf("lower", (x, y, zc), q1, 1, obj, speed=0.15)
        rel = self.kf("release", (x, y, zc), q1, 0, obj, settle=2)  # 0.2 s, see place()
        self.kf("retreat", (x - 0.10 * math.cos(a), y - 0.10 * math.sin(a), zc + 0.02), q1, 0, obj, speed=0.2)
        self.update(release_kf=rel)

    # -- insertion ------------------------------------------------------------------------------------
    def insert_top(self, obj: str, hole: str) -> None:
        """Lower a rod held top-down into a rack hole (its lower end onto the rack's base plate)."""
        g = self.grip_offset(obj)
        half = self.scene.objects[obj].dims["length"] / 2
        x, y, _ = self._where(hole)
        zb = 0.008 + half + g[2]  # end effector height with the rod standing on the base plate
        q = top_down(0.0)
        self.step("insert", object=obj, dest=hole, dest_xy=[float(x), float(y)])
        self.kf("above", (x, y, assets.RACK_HEIGHT + 0.03 + half + g[2]), q, 1, hole)
        self.kf("down", (x, y, zb), q, 1, hole, speed=0.12, settle=4)

    def insert_side(self, obj: str, hole: str) -> None:
        """Push a peg held top-down sideways into a hole: align its head with the hole's axis a little in
        front of the opening, slide in to the goal pose, release (PegInsertionSide)."""
        o = self.scene.objects[obj]
        goal_p = np.asarray(self.scene.extra["peg_goal_p"], float)
        goal_r = quat_to_matrix(tuple(self.scene.extra["peg_goal_q"]))
        body0 = quat_to_matrix(o.body_quat)
        hold = next(k for k in reversed(self.keyframes) if k.gripper == 1 and k.segment == self.steps[-1].index)
        # The hand keeps its pose relative to the peg: T_hand(goal) = T_goal T_peg0^-1 T_hand(grasp).
        hand0_r = quat_to_matrix(hold.quat)
        hand0_p = np.asarray(self.keyframes[[k.name for k in self.keyframes].index(self.steps[-1].close_kf)].pos)
        rel_r = body0.T @ hand0_r
        rel_p = body0.T @ (hand0_p - np.asarray(o.pos))
        r = goal_r @ rel_r
        q = matrix_to_quat(r)
        axis = goal_r[:, 0]  # the hole's axis, into the box
        half = o.dims["length"] / 2
        p_in = goal_p + goal_r @ rel_p
        p_pre = p_in - (half + 0.02) * axis
        self.step("insert", object=obj, dest=hole, dest_xy=[float(goal_p[0]), float(goal_p[1])])
        self.kf("align", p_pre + np.array([0, 0, 0.05]), q, 1, hole)
        self.kf("front", p_pre, q, 1, hole, speed=0.15, settle=4)
        self.kf("slide", p_in, q, 1, hole, speed=0.05, settle=4)
        rel = self.kf("release", p_in, q, 0, hole, settle=2)  # 0.2 s, see place()
        self.kf("retreat", p_in + np.array([0, 0, 0.08]), q, 0, hole, speed=0.2)
        self.update(release_kf=rel)

    # -- articulations --------------------------------------------------------------------------------
    def _door_bypass(self, oven: str, z: float) -> list[tuple[float, float, float]]:
        """Waypoints round the free edge of the open door (outside face first, then the opening)."""
        o = self.scene.objects[oven]
        hinge_x = o.pos[0] - o.dims["depth"] / 2
        free = assets.handle_position(o.pos, assets.DOOR_OPEN)
        x = min(free[0], hinge_x - o.dims["width"]) - 0.07
        return [(x, free[1] - 0.10, z), (x, o.pos[1], z)]

    def door(self, oven: str, to_open: bool, arc_points: int = 6) -> None:
        """Grasp the vertical handle and swing it along the hinge arc; release and back off."""
        o = self.scene.objects[oven]
        # Closing stops just short of the stop: pushed into its limit the door binds the fingers.
        a0, a1 = (0.0, assets.DOOR_OPEN) if to_open else (assets.DOOR_OPEN, 0.05)
        self.step("open" if to_open else "close", object=oven, target_angle=a1)
        h0 = assets.handle_position(o.pos, a0)
        if not to_open:
            for i, wp in enumerate(reversed(self._door_bypass(oven, h0[2]))):
                self.kf(f"bypass{i}", wp, side(), 0, oven)
        out0 = np.array([-math.cos(a0), -math.sin(a0), 0.0]) * 0.10
        pre = self.kf("pre", h0 + out0, side(a0), 0, oven)
        if not to_open:  # from the bypass the hand turns to face the open door: a turn between families
            self.joint_space.add(pre)
        self.kf("reach", h0, side(a0), 0, oven, speed=0.2)
        self.kf("grip", h0, side(a0), 1, oven, settle=8)
        for i in range(1, arc_points + 1):
            a = a0 + (a1 - a0) * i / arc_points
            self.kf(f"arc{i}", assets.handle_position(o.pos, a), side(a), 1, oven, speed=0.12)
        h1 = assets.handle_position(o.pos, a1)
        out1 = np.array([-math.cos(a1), -math.sin(a1), 0.0]) * 0.10
        self.kf("let_go", h1, side(a1), 0, oven, settle=10)
        self.kf("retreat", h1 + out1, side(a1), 0, oven)
        if to_open:
            for i, wp in enumerate(self._door_bypass(oven, h1[2])):
                self.kf(f"bypass{i}", wp, side(), 0, oven)
        self.update(contact_kf=f"s{self.steps[-1].index}_grip", contact_point=[float(v) for v in h0])

    def push_shut(self, oven: str, arc_points: int = 6) -> None:
        """Close the open door by pushing its outer face near the free edge with the closed fingers, the
        hand pointing down, along the hinge arc. (Grasping the handle of the open door needs the hand
        turned sideways next to the robot's base, a pose the Panda barely reaches; PyBullet grasps.)"""
        o = self.scene.objects[oven]
        d, w = o.dims["depth"], o.dims["width"]
        hinge = np.array([o.pos[0] - d / 2, o.pos[1] - w / 2])
        # Push half way out along the door (the handle near the free edge would catch the fingers), the
        # fingertips at mid-height.
        r, z = 0.5 * w, o.pos[2] + 0.11
        q = top_down(0.0)
        a0, a1 = assets.DOOR_OPEN, 0.06

        def at(a: float, out: float) -> tuple[float, float, float]:
            c, s_ = math.cos(a), math.sin(a)
            lx = -0.01 - 0.012 - out  # outside the door's outer face (door frame x), by the fingers' half width
            return (float(hinge[0] + lx * c - r * s_), float(hinge[1] + lx * s_ + r * c), z)

        self.step("close", object=oven, target_angle=a1)
        above = at(a0, 0.08)
        self.kf("above", (above[0], above[1], o.pos[2] + o.dims["height"] + 0.08), q, 1, oven)  # over the door
        self.kf("pre", above, q, 1, oven)
        touch = self.kf("touch", at(a0, 0.0), q, 1, oven, speed=0.15)
        for i in range(1, arc_points + 1):
            self.kf(f"arc{i}", at(a0 + (a1 - a0) * i / arc_points, 0.0), q, 1, oven, speed=0.12)
        self.kf("retreat", at(a1, 0.10), q, 1, oven, speed=0.2)
        self.update(contact_kf=touch, contact_point=list(at(a0, 0.0)))

    def press(self, button: str) -> None:
        """Push the button's cap down with the closed fingers (reported as the atomic action `close`)."""
        o = self.scene.objects[button]
        x, y, _ = o.pos
        top = o.dims["top"]
        q = top_down(0.0)
        self.step("close", object=button)
        self.kf("above", (x, y, top + 0.08), q, 1, button, settle=5)
        self.kf("touch", (x, y, top + 0.012), q, 1, button, speed=0.2)
        self.kf("press", (x, y, top - 0.006), q, 1, button, speed=0.04, settle=5)
        self.kf("release", (x, y, top + 0.08), q, 1, button, speed=0.2)
        self.update(contact_kf=f"s{self.steps[-1].index}_press", contact_point=[float(x), float(y), top - 0.006])
