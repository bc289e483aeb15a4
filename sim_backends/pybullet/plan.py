"""Keyframe plan builder and reusable skills (grasp, place, pour, stir, shake, insert, door, press).

A template composes skills into steps; every step is one atomic action of
the paper's vocabulary and becomes one keyframe segment. The builder also
records what the labeler needs to check the step from state (`steps`) and
the task's goals (`goals`) as the typed `Step`/`Goal` of sim_backends/schema.py.
"""

from __future__ import annotations

import math

import numpy as np
import pybullet as p

from sim_backends.plan_builder import PlanBuilder
from sim_backends.pybullet import assets
from sim_backends.pybullet.robot import SIDE, TOP_DOWN
from sim_backends.pybullet.scene import Scene

SAFE_Z = 0.26  # transport height of the end effector
POUR_SIGN = 1.0
POUR_REACH = 0.8  # grasp point beside dest, as a fraction of the grasp-to-mouth length


def _yaw(angle: float, quat=SIDE) -> tuple:
    """Rotate a gripper orientation about the world z axis (to follow a swinging door)."""
    return p.multiplyTransforms([0, 0, 0], p.getQuaternionFromEuler([0, 0, angle]), [0, 0, 0], quat)[1]


def _roll(quat, angle: float) -> tuple:
    """Rotate a gripper orientation about its own approach (z) axis."""
    return p.multiplyTransforms([0, 0, 0], quat, [0, 0, 0], p.getQuaternionFromEuler([0, 0, angle]))[1]


class Plan(PlanBuilder):
    """The PyBullet skills on the backend-neutral builder; `scene` gives the objects and zones."""

    DEFAULT_SPEED = 0.45

    def __init__(self, scene: Scene):
        super().__init__()
        self.scene = scene
        self.moved: dict[str, tuple[float, float, float]] = {}  # where earlier steps put objects

    def _obj(self, name: str):
        return self.scene.objects[name]

    def _at(self, name: str) -> tuple[float, float, float]:
        """Where an object stands when this step starts: its home, or where an earlier step placed it."""
        return self.moved.get(name, self.scene.objects[name].home)

    # -- skills ---------------------------------------------------------------------------------------
    def grasp(self, obj: str, inside: bool = False) -> None:
        """Side grasp of a vessel (approach along +x) or top-down grasp of a rod.

        `inside`: the object stands in the oven, so lift only a little and withdraw horizontally.
        """
        o = self._obj(obj)
        x, y, z = self._at(obj)
        self.step("grasp", object=obj)
        if o.kind == "vessel":
            zg = z + min(0.6 * o.dims["height"], 0.048)  # low grasps near the base trap the IK
            self.kf("pre", (x - 0.13, y, zg), SIDE, 0, obj)
            self.kf("reach", (x - 0.005, y, zg), SIDE, 0, obj, speed=0.25)
            close = self.kf("close", (x - 0.005, y, zg), SIDE, 1, obj, settle=50)
            if inside:
                self.kf("lift", (x - 0.005, y, zg + 0.02), SIDE, 1, obj, speed=0.2)
                self.kf("withdraw", (x - 0.25, y, zg + 0.02), SIDE, 1, obj, speed=0.25)
            else:
                self.kf("lift", (x - 0.005, y, zg + 0.12), SIDE, 1, obj, speed=0.3)
            self.update(close_kf=close, grip_offset=[-0.005, 0.0, zg - z], width=2 * o.dims["radius"] + 0.004)
        else:
            top = z + o.dims["length"] / 2
            zg = top - 0.035
            self.kf("pre", (x, y, top + 0.06), TOP_DOWN, 0, obj)
            self.kf("reach", (x, y, zg), TOP_DOWN, 0, obj, speed=0.25)
            close = self.kf("close", (x, y, zg), TOP_DOWN, 1, obj, settle=50)
            self.kf("lift", (x, y, zg + o.dims["length"] * 0.75 + 0.02), TOP_DOWN, 1, obj, speed=0.3)
            self.update(close_kf=close, grip_offset=[0.0, 0.0, zg - z], width=2 * o.dims["radius"])

    def place(self, obj: str, dest: str, returning: bool = False, inside: bool = False) -> None:
        """Carry the held object to a zone (or back home) and release it there.

        `inside`: the zone is in the oven, so come in low and horizontally.
        """
        o = self._obj(obj)
        g = self.grip_offset(obj)
        dx, dy = self.scene.zones[dest][:2] if dest in self.scene.zones else o.home[:2]
        quat = SIDE if o.kind == "vessel" else TOP_DOWN
        zr = assets.BENCH_TOP + g[2] + 0.004
        self.step("place", object=obj, dest=dest, dest_xy=[dx, dy], returning=returning)
        if inside:
            self.kf("carry", (dx + g[0] - 0.25, dy + g[1], zr + 0.02), quat, 1, dest)
            self.kf("enter", (dx + g[0], dy + g[1], zr + 0.02), quat, 1, dest, speed=0.25)
        else:
            self.kf("carry", (dx + g[0], dy + g[1], max(zr + 0.12, 0.16)), quat, 1, dest)
        self.kf("lower", (dx + g[0], dy + g[1], zr), quat, 1, dest, speed=0.2)
        rel = self.kf("release", (dx + g[0], dy + g[1], zr), quat, 0, dest, settle=40)
        back = (-0.12, 0, 0) if o.kind == "vessel" else (0, 0, 0.1)
        self.kf("retreat", (dx + g[0] + back[0], dy + g[1], zr + back[2]), quat, 0, dest, speed=0.3)
        self.steps[-1].release_kf = rel
        self.moved[obj] = (dx, dy, o.home[2] if dest not in self.scene.zones else self.scene.zones[dest][2])

    def pour(self, src: str, dest: str, side: float = -1.0) -> None:
        """Bring the held vessel beside `dest` and roll it progressively until the liquid has run out."""
        d = self._obj(dest)
        s = self._obj(src)
        g = self.grip_offset(src)
        x, y, z = d.home
        rim = z + d.dims["height"]
        mouth = s.dims["height"] - g[2]  # from the grasp point to the mouth of the held vessel
        # Hold the grasp point beside dest so that, fully tilted, the mouth is above dest's centre.
        ay = y + side * POUR_REACH * mouth
        zc = rim + 0.065
        self.step("pour", object=src, dest=dest)
        self.kf("align", (x + g[0], ay, zc + 0.05), SIDE, 1, dest)
        self.kf("lower", (x + g[0], ay, zc), SIDE, 1, dest, speed=0.2)
        for i, ang in enumerate((0.9, 1.5, 2.0)):
            self.kf(f"tilt{i}", (x + g[0], ay, zc), _roll(SIDE, POUR_SIGN * side * ang), 1, dest, speed=0.2, settle=40)
        self.kf("upright", (x + g[0], ay, zc + 0.04), SIDE, 1, dest, speed=0.3)

    def shake(self, obj: str, amp: float = 0.05, n: int = 3, speed: float = 0.6) -> None:
        o = self._obj(obj)
        x, y, _ = o.home
        self.step("shake", object=obj)
        zc = SAFE_Z - 0.06
        for i in range(n):
            self.kf(f"left{i}", (x - 0.005, y - amp, zc), SIDE, 1, obj, speed=speed)
            self.kf(f"right{i}", (x - 0.005, y + amp, zc), SIDE, 1, obj, speed=speed)

    def _ee_z_for_bottom(self, obj: str, bottom: float) -> float:
        """End-effector height that puts the lower end of a held rod at `bottom`."""
        return bottom + 0.5 * self._obj(obj).dims["length"] + self.grip_offset(obj)[2]

    def insert(self, obj: str, into: str) -> None:
        """Lower a held rod (top-down grasp) into a vessel or a rack hole.

        The approach keyframe keeps the rod's lower end 3 cm above the rim/top plate, so the carry
        never sweeps the rod through the destination.
        """
        if into in self.scene.objects:  # a vessel: stop 1.5 cm above its floor
            v = self.scene.objects[into]
            x, y, z = self._at(into)
            bottom, top = z + 0.015, z + v.dims["height"]
        else:  # a rack hole: stand on the rack's base plate
            x, y, z = self.scene.zones[into]
            bottom, top = z + 0.008, z + assets.RACK_HEIGHT
        self.step("insert", object=obj, dest=into, dest_xy=[x, y])
        self.kf("above", (x, y, self._ee_z_for_bottom(obj, top + 0.03)), TOP_DOWN, 1, into)
        self.kf("down", (x, y, self._ee_z_for_bottom(obj, bottom)), TOP_DOWN, 1, into, speed=0.15, settle=20)

    def stir(self, obj: str, vessel: str, amp: float = 0.01, n: int = 3) -> None:
        v = self.scene.objects[vessel]
        x, y, z = self._at(vessel)
        zc = self._ee_z_for_bottom(obj, z + 0.015)
        self.step("stir", object=obj, dest=vessel)
        for i in range(n):
            self.kf(f"a{i}", (x, y - amp, zc), TOP_DOWN, 1, vessel, speed=0.1)
            self.kf(f"b{i}", (x, y + amp, zc), TOP_DOWN, 1, vessel, speed=0.1)
        self.kf("out", (x, y, self._ee_z_for_bottom(obj, z + v.dims["height"] + 0.03)), TOP_DOWN, 1, vessel, speed=0.2)

    def _door_bypass(self, oven: str, z: float) -> list[tuple[float, float, float]]:
        """Waypoints around the free edge of the open door: outside face first, then the opening.

        The open door stands across the path between the bench in front of the hinge side and the
        oven's opening; the arm must go round its free edge, never through it.
        """
        o = self._obj(oven)
        hinge_x = o.home[0] - o.dims["depth"] / 2
        free = assets.handle_position(o.home, assets.DOOR_OPEN)
        x = min(free[0], hinge_x - o.dims["width"]) - 0.07
        return [(x, free[1] - 0.10, z), (x, o.home[1], z)]

    def door(self, oven: str, to_open: bool, arc_points: int = 6) -> None:
        """Grasp the vertical handle and swing it along the hinge arc; release and back off."""
        o = self._obj(oven)
        a0, a1 = (0.0, assets.DOOR_OPEN) if to_open else (assets.DOOR_OPEN, 0.0)
        self.step("open" if to_open else "close", object=oven, target_angle=a1)
        h0 = assets.handle_position(o.home, a0)
        if not to_open:  # come from the opening round to the outside face of the open door
            for i, wp in enumerate(reversed(self._door_bypass(oven, h0[2]))):
                self.kf(f"bypass{i}", wp, SIDE, 0, oven)
        out0 = np.array([-math.cos(a0), -math.sin(a0), 0.0]) * 0.10  # away from the door face
        self.kf("pre", h0 + out0, _yaw(a0), 0, oven)
        self.kf("reach", h0, _yaw(a0), 0, oven, speed=0.2)
        self.kf("grip", h0, _yaw(a0), 1, oven, settle=40)
        for i in range(1, arc_points + 1):
            a = a0 + (a1 - a0) * i / arc_points
            self.kf(f"arc{i}", assets.handle_position(o.home, a), _yaw(a), 1, oven, speed=0.15)
        h1 = assets.handle_position(o.home, a1)
        out1 = np.array([-math.cos(a1), -math.sin(a1), 0.0]) * 0.10
        self.kf("let_go", h1, _yaw(a1), 0, oven, settle=25)
        self.kf("retreat", h1 + out1, _yaw(a1), 0, oven)
        if to_open:  # end in front of the opening, ready to reach inside
            for i, wp in enumerate(self._door_bypass(oven, h1[2])):
                self.kf(f"bypass{i}", wp, SIDE, 0, oven)
        self.update(contact_kf=f"s{self.steps[-1].index}_grip", contact_point=[float(v) for v in h0])

    def press(self, button: str) -> None:
        o = self._obj(button)
        x, y, _ = o.home
        top = o.dims["top"]
        self.step("close", object=button)  # pressing is a closed-gripper push (see docs/ARCHITECTURE.md)
        self.kf("above", (x, y, top + 0.08), TOP_DOWN, 1, button, settle=30)
        self.kf("touch", (x, y, top + 0.015), TOP_DOWN, 1, button, speed=0.2)
        self.kf("press", (x, y, top - 0.004), TOP_DOWN, 1, button, speed=0.05, settle=30)
        self.kf("release", (x, y, top + 0.08), TOP_DOWN, 1, button, speed=0.2)
        self.update(contact_kf=f"s{self.steps[-1].index}_press", contact_point=[x, y, top - 0.004])

    def home(self) -> None:
        """A neutral pose between sub-tasks (part of the previous step)."""
        st = self.steps[-1]
        self.kf(
            "home",
            (0.4, 0.0, SAFE_Z + 0.05),
            SIDE if st.action != "insert" else TOP_DOWN,
            self.keyframes[-1].gripper,
            self.keyframes[-1].target,
        )
