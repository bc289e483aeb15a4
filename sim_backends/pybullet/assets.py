"""Chemistry-lab bench assets built from PyBullet primitives in code (no mesh files).

Compound shapes stay at 16 parts or fewer: `createVisualShapeArray` segfaults above that.
Every builder returns body ids; the scene keeps a name -> body map.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pybullet as p

GLASS = (0.70, 0.88, 0.95, 1.0)
BENCH_TOP = 0.0  # world z of the bench surface; the robot stands on it
FLOOR_Z = -0.75
LIQUID_DAMPING = 1.5  # viscous drag on liquid particles; low values let a tilt fling them off the bench


def _part_arrays(parts: Sequence[tuple], frame: str) -> dict[str, list]:
    """A part list's shape arrays, as the keywords of `createCollisionShapeArray` (`frame="collision"`) or
    `createVisualShapeArray` (`frame="visual"`): (half_extents, local_pos, local_orn) boxes, or ('cyl', radius,
    length, local_pos) cylinders."""
    assert len(parts) <= 16, "compound shapes above 16 parts crash PyBullet's visual arrays"
    cyl = [q[0] == "cyl" for q in parts]
    return {
        "shapeTypes": [p.GEOM_CYLINDER if c else p.GEOM_BOX for c in cyl],
        "halfExtents": [[0, 0, 0] if c else q[0] for c, q in zip(cyl, parts)],
        "radii": [q[1] if c else 0 for c, q in zip(cyl, parts)],
        "lengths": [q[2] if c else 0 for c, q in zip(cyl, parts)],
        f"{frame}FramePositions": [q[3] if c else q[1] for c, q in zip(cyl, parts)],
        f"{frame}FrameOrientations": [(0, 0, 0, 1) if c else q[2] for c, q in zip(cyl, parts)],
    }


def _visual_array(cid: int, parts: Sequence[tuple], rgba) -> int:
    return p.createVisualShapeArray(
        **_part_arrays(parts, "visual"), rgbaColors=[tuple(rgba)] * len(parts), physicsClientId=cid
    )


def _compound(
    cid: int, parts: Sequence[tuple], mass: float, pos, orn=(0, 0, 0, 1), rgba=GLASS, friction: float = 0.8
) -> int:
    """parts: (half_extents, local_pos, local_orn) boxes, or ('cyl', radius, length, local_pos) cylinders."""
    col = p.createCollisionShapeArray(**_part_arrays(parts, "collision"), physicsClientId=cid)
    body = p.createMultiBody(mass, col, _visual_array(cid, parts, rgba), pos, orn, physicsClientId=cid)
    p.changeDynamics(
        body, -1, lateralFriction=friction, spinningFriction=0.002, rollingFriction=0.0005, physicsClientId=cid
    )
    return body


@dataclass
class VesselSpec:
    radius: float = 0.03
    height: float = 0.09
    sides: int = 8
    wall: float = 0.007
    mass: float = 0.12
    rgba: tuple = GLASS
    neck_radius: float = 0.0  # > 0: an Erlenmeyer flask (walls lean in towards a narrow neck)


def vessel(cid: int, spec: VesselSpec, pos) -> int:
    """Hollow glassware: an n-gon of wall plates plus a bottom; open at the top so liquid can flow in and out.

    With `neck_radius` the upper half of each wall leans inwards (an Erlenmeyer silhouette).
    The body frame is at the bottom centre.
    """
    n, r, h, t = spec.sides, spec.radius, spec.height, spec.wall
    parts: list[tuple] = [((r * 0.95, r * 0.95, t / 2), (0, 0, t / 2), (0, 0, 0, 1))]
    side = 2 * r * math.tan(math.pi / n) + t
    flask = spec.neck_radius > 0
    low_h = h * 0.5 if flask else h
    # The walls stand on the bottom plate. Walls reaching down to the bench touched it (and the liquid resting
    # on the bottom) at 4 contact points each: 3x the contacts and 2.4x the physics time of a resting vessel.
    wall_h = low_h - t
    for i in range(n):
        a = 2 * math.pi * (i + 0.5) / n
        c, s = math.cos(a), math.sin(a)
        parts.append(
            ((t / 2, side / 2, wall_h / 2), (c * r, s * r, t + wall_h / 2), p.getQuaternionFromEuler([0, 0, a]))
        )
    if flask:
        up_h = h - low_h
        inset = r - spec.neck_radius
        lean = math.atan2(inset, up_h)
        slant = math.hypot(inset, up_h)
        rm = (r + spec.neck_radius) / 2
        side_up = 2 * rm * math.tan(math.pi / n) + t
        for i in range(n):
            a = 2 * math.pi * (i + 0.5) / n
            c, s = math.cos(a), math.sin(a)
            # Yaw to face outwards, then lean the plate about its tangent axis towards the axis of the flask.
            q = p.multiplyTransforms(
                [0, 0, 0], p.getQuaternionFromEuler([0, 0, a]), [0, 0, 0], p.getQuaternionFromEuler([0, -lean, 0])
            )[1]
            parts.append(((t / 2, side_up / 2, slant / 2), (c * rm, s * rm, low_h + up_h / 2), q))
    return _compound(cid, parts, spec.mass, pos, rgba=spec.rgba, friction=0.9)


def rod(cid: int, pos, length: float = 0.22, radius: float = 0.006, rgba=(0.85, 0.95, 1.0, 1.0)) -> int:
    """Glass rod standing upright; body frame at its centre."""
    col = p.createCollisionShape(p.GEOM_CYLINDER, radius=radius, height=length, physicsClientId=cid)
    vis = p.createVisualShape(p.GEOM_CYLINDER, radius=radius, length=length, rgbaColor=rgba, physicsClientId=cid)
    b = p.createMultiBody(0.03, col, vis, pos, physicsClientId=cid)
    p.changeDynamics(b, -1, lateralFriction=1.0, rollingFriction=0.001, spinningFriction=0.002, physicsClientId=cid)
    return b


RACK_HEIGHT = 0.06


def rack(
    cid: int,
    pos,
    holes: int = 3,
    pitch: float = 0.05,
    hole: float = 0.024,
    height: float = RACK_HEIGHT,
    rgba=(0.55, 0.38, 0.22, 1.0),
) -> int:
    """Test-tube rack: a base plate, two end walls and a top plate with square holes along y."""
    t = 0.006
    length = holes * pitch
    depth = 0.05
    parts: list[tuple] = [((depth / 2, length / 2, t / 2), (0, 0, t / 2), (0, 0, 0, 1))]
    for sgn in (-1, 1):  # end walls
        parts.append(((depth / 2, t / 2, height / 2), (0, sgn * (length / 2 - t / 2), height / 2), (0, 0, 0, 1)))
    rim = (depth - hole) / 4
    for sgn in (-1, 1):  # front and back bars of the top plate
        parts.append(((rim, length / 2, t / 2), (sgn * (hole / 2 + rim), 0, height - t / 2), (0, 0, 0, 1)))
    for i in range(holes + 1):  # separators between the holes
        y = -length / 2 + i * pitch
        w = (pitch - hole) / 2 if 0 < i < holes else (pitch - hole) / 4
        yc = y if 0 < i < holes else y + (w if i == 0 else -w)
        parts.append(((hole / 2, w, t / 2), (0, yc, height - t / 2), (0, 0, 0, 1)))
    return _compound(cid, parts, 0.0, pos, rgba=rgba)


def hole_positions(rack_pos, holes: int = 3, pitch: float = 0.05) -> list[tuple[float, float]]:
    length = holes * pitch
    return [(rack_pos[0], rack_pos[1] - length / 2 + pitch * (i + 0.5)) for i in range(holes)]


def zone(cid: int, pos, radius: float = 0.05, rgba=(0.2, 0.8, 0.3, 1.0)) -> int:
    """A flat coloured target mark on the bench (visual only)."""
    vis = p.createVisualShape(p.GEOM_CYLINDER, radius=radius, length=0.001, rgbaColor=rgba, physicsClientId=cid)
    return p.createMultiBody(0, -1, vis, [pos[0], pos[1], BENCH_TOP + 0.0006], physicsClientId=cid)


def bench(cid: int, rgba=(0.82, 0.80, 0.76, 1.0), floor_rgba=(0.35, 0.35, 0.38, 1.0)) -> tuple[int, int]:
    he = [0.5, 0.65, 0.02]
    col = p.createCollisionShape(p.GEOM_BOX, halfExtents=he, physicsClientId=cid)
    vis = p.createVisualShape(p.GEOM_BOX, halfExtents=he, rgbaColor=rgba, physicsClientId=cid)
    top = p.createMultiBody(0, col, vis, [0.45, 0, BENCH_TOP - he[2]], physicsClientId=cid)
    fcol = p.createCollisionShape(p.GEOM_BOX, halfExtents=[3, 3, 0.01], physicsClientId=cid)
    fvis = p.createVisualShape(p.GEOM_BOX, halfExtents=[3, 3, 0.01], rgbaColor=floor_rgba, physicsClientId=cid)
    floor = p.createMultiBody(0, fcol, fvis, [0, 0, FLOOR_Z - 0.01], physicsClientId=cid)
    p.changeDynamics(top, -1, lateralFriction=0.8, physicsClientId=cid)
    return top, floor


def particles(
    cid: int,
    centre,
    count: int,
    radius: float = 0.0065,
    mass: float = 0.002,
    rgba=(0.2, 0.45, 0.95, 1.0),
    spread: float = 0.012,
) -> list[int]:
    """Liquid as small spheres stacked in a column above `centre` (they settle into the vessel)."""
    col = p.createCollisionShape(p.GEOM_SPHERE, radius=radius, physicsClientId=cid)
    vis = p.createVisualShape(p.GEOM_SPHERE, radius=radius, rgbaColor=rgba, physicsClientId=cid)
    ids = []
    per_layer = 4
    for i in range(count):
        layer, k = divmod(i, per_layer)
        a = math.pi / 2 * k + 0.4 * layer
        x = centre[0] + spread * math.cos(a)
        y = centre[1] + spread * math.sin(a)
        z = centre[2] + radius + 2.05 * radius * layer
        b = p.createMultiBody(mass, col, vis, [x, y, z], physicsClientId=cid)
        p.changeDynamics(
            b,
            -1,
            lateralFriction=0.05,
            rollingFriction=0.0,
            spinningFriction=0.0,
            restitution=0.0,
            linearDamping=LIQUID_DAMPING,
            ccdSweptSphereRadius=0.8 * radius,
            physicsClientId=cid,
        )
        ids.append(b)
    return ids


def shards(cid: int, centre, radius: float, rgba, stub: bool = True) -> int:
    """Broken glassware, drawn only: six flat pieces scattered 1.5-2.4 radii around `centre` (x, y, z of the surface
    it lies on), with a vessel's bottom stub and three short jagged walls in the middle (`stub`; a rod has none). A
    visual shape without a collision shape or mass, so the physics and every label stay as they were
    (`broken_glass`). Deterministic: no random draw, so the episode's stream is untouched."""
    yaw = lambda a: p.getQuaternionFromEuler([0.0, 0.0, a])  # noqa: E731
    parts: list[tuple] = []
    if stub:
        parts.append(("cyl", 0.8 * radius, 0.006, (0.0, 0.0, 0.003)))
        for k in range(3):  # wall stubs on the rim, 15-27 mm high
            a, h = 2.1 * k + 0.4, 0.0075 + 0.003 * k
            parts.append(((0.006, 0.0015, h), (0.75 * radius * math.cos(a), 0.75 * radius * math.sin(a), h), yaw(a)))
    for k in range(6):
        a = 1.05 * k + 0.2 * (k % 2)
        d = radius * (1.5 + 0.2 * (k % 3) + 0.1 * k)
        half = (0.009 + 0.002 * (k % 3), 0.005 + 0.002 * (k % 2), 0.0012)
        parts.append((half, (d * math.cos(a), d * math.sin(a), 0.0012), yaw(1.7 * a)))
    return p.createMultiBody(0, -1, _visual_array(cid, parts, rgba), centre, physicsClientId=cid)


def oven(
    cid: int,
    pos,
    width: float = 0.24,
    depth: float = 0.22,
    height: float = 0.18,
    open_angle: float = 0.0,
    rgba=(0.88, 0.88, 0.86, 1.0),
    door_rgba=(0.55, 0.62, 0.68, 1.0),
) -> tuple[int, int]:
    """Drying oven: a fixed cabinet open at the front (towards the robot, -x) closed by a door hinged on a
    vertical axis at its front right edge (seen from the robot, y < 0). A vertical round handle sits near
    the door's free edge.

    Returns (body, door_joint). Door angle 0 = closed, pi/2 = swung fully open towards the robot.
    `pos` is the centre of the cabinet's floor.
    """
    t = 0.01
    w2, d2, h = width / 2, depth / 2, height
    parts = [
        ((d2, w2, t / 2), (0, 0, t / 2)),  # floor
        ((d2, w2, t / 2), (0, 0, h - t / 2)),  # roof
        ((t / 2, w2, h / 2), (d2 - t / 2, 0, h / 2)),  # back
        ((d2, t / 2, h / 2), (0, -w2 + t / 2, h / 2)),  # sides
        ((d2, t / 2, h / 2), (0, w2 - t / 2, h / 2)),
    ]
    body_col = p.createCollisionShapeArray(
        shapeTypes=[p.GEOM_BOX] * 5,
        halfExtents=[q[0] for q in parts],
        collisionFramePositions=[q[1] for q in parts],
        physicsClientId=cid,
    )
    body_vis = p.createVisualShapeArray(
        shapeTypes=[p.GEOM_BOX] * 5,
        halfExtents=[q[0] for q in parts],
        visualFramePositions=[q[1] for q in parts],
        rgbaColors=[rgba] * 5,
        physicsClientId=cid,
    )
    # Door link frame = the hinge line; the closed door plate spans +y from it, its outer face towards -x.
    hy = width - 0.035  # handle distance from the hinge along the door
    dark = (0.2, 0.2, 0.2, 1)
    d_types = [p.GEOM_BOX, p.GEOM_CYLINDER, p.GEOM_BOX, p.GEOM_BOX]
    d_he = [(t / 2, w2, h / 2 - 0.004), (0, 0, 0), (0.016, 0.006, 0.006), (0.016, 0.006, 0.006)]  # clears the bench
    d_pos = [
        (-t / 2, w2, h / 2 + 0.003),
        HANDLE_OFFSET[:2] + (h / 2,),
        (-0.018, hy, h / 2 - 0.045),
        (-0.018, hy, h / 2 + 0.045),
    ]
    door_col = p.createCollisionShapeArray(
        shapeTypes=d_types,
        halfExtents=d_he,
        radii=[0, 0.007, 0, 0],
        lengths=[0, 0.11, 0, 0],
        collisionFramePositions=d_pos,
        physicsClientId=cid,
    )
    door_vis = p.createVisualShapeArray(
        shapeTypes=d_types,
        halfExtents=d_he,
        radii=[0, 0.007, 0, 0],
        lengths=[0, 0.11, 0, 0],
        visualFramePositions=d_pos,
        rgbaColors=[door_rgba, dark, dark, dark],
        physicsClientId=cid,
    )
    body = p.createMultiBody(
        0,
        body_col,
        body_vis,
        pos,
        linkMasses=[0.5],
        linkCollisionShapeIndices=[door_col],
        linkVisualShapeIndices=[door_vis],
        linkPositions=[[-d2, -w2, 0.0]],
        linkOrientations=[[0, 0, 0, 1]],
        linkInertialFramePositions=[[-t / 2, w2, h / 2]],
        linkInertialFrameOrientations=[[0, 0, 0, 1]],
        linkParentIndices=[0],
        linkJointTypes=[p.JOINT_REVOLUTE],
        linkJointAxis=[[0, 0, 1]],
        physicsClientId=cid,
    )
    p.changeDynamics(
        body,
        0,
        jointLowerLimit=0.0,
        jointUpperLimit=math.radians(100),
        lateralFriction=1.0,
        jointDamping=0.05,
        physicsClientId=cid,
    )
    p.resetJointState(body, 0, open_angle, physicsClientId=cid)
    # Hinge friction holds the door where it is left (a real oven door does not swing on its own).
    p.setJointMotorControl2(body, 0, p.VELOCITY_CONTROL, targetVelocity=0, force=0.8, physicsClientId=cid)
    return body, 0


HANDLE_OFFSET = (-0.035, 0.24 - 0.035)  # handle axis in the door frame (x, y), for the default width


DOOR_OPEN = math.radians(80)  # the planned open angle (the plan bypasses the door's free edge)


def handle_position(
    oven_pos, angle: float, depth: float = 0.22, width: float = 0.24, height: float = 0.18
) -> np.ndarray:
    """World position of the door handle's centre for a door angle (used to plan keyframes)."""
    hinge = np.array([oven_pos[0] - depth / 2, oven_pos[1] - width / 2, oven_pos[2]])
    lx, ly = HANDLE_OFFSET
    c, s = math.cos(angle), math.sin(angle)
    return hinge + np.array([lx * c - ly * s, lx * s + ly * c, height / 2])


HOUSING_RGBA = (0.25, 0.25, 0.28, 1.0)  # a button's housing, dark grey
LAMP_RGBA = (1.0, 0.15, 0.85, 1.0)  # the housing lit once pressed (`button_lamp`): magenta, a hue no cap has


def button(cid: int, pos, rgba=(0.85, 0.1, 0.1, 1.0), travel: float = 0.012) -> tuple[int, int]:
    """Push button: a fixed housing and a cap on a sprung prismatic joint (spring = position motor)."""
    hcol = p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.04, 0.04, 0.02], physicsClientId=cid)
    hvis = p.createVisualShape(p.GEOM_BOX, halfExtents=[0.04, 0.04, 0.02], rgbaColor=HOUSING_RGBA, physicsClientId=cid)
    ccol = p.createCollisionShape(p.GEOM_CYLINDER, radius=0.022, height=0.02, physicsClientId=cid)
    cvis = p.createVisualShape(p.GEOM_CYLINDER, radius=0.022, length=0.02, rgbaColor=rgba, physicsClientId=cid)
    body = p.createMultiBody(
        0,
        hcol,
        hvis,
        [pos[0], pos[1], BENCH_TOP + 0.02],
        linkMasses=[0.05],
        linkCollisionShapeIndices=[ccol],
        linkVisualShapeIndices=[cvis],
        linkPositions=[[0, 0, 0.03]],
        linkOrientations=[[0, 0, 0, 1]],
        linkInertialFramePositions=[[0, 0, 0]],
        linkInertialFrameOrientations=[[0, 0, 0, 1]],
        linkParentIndices=[0],
        linkJointTypes=[p.JOINT_PRISMATIC],
        linkJointAxis=[[0, 0, -1]],
        physicsClientId=cid,
    )
    p.changeDynamics(body, 0, jointLowerLimit=0.0, jointUpperLimit=travel, physicsClientId=cid)
    p.setJointMotorControl2(body, 0, p.POSITION_CONTROL, 0.0, force=4.0, physicsClientId=cid)
    return body, 0
