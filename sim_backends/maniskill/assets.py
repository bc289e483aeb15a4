"""Lab props built in code with SAPIEN/ManiSkill builders: glassware, rod, rack, button, oven, zones.

ManiSkill ships no lab equipment that works offline (its PartNet cabinets need a download), so
these are made from primitives, with the geometry of the PyBullet backend's props
(sim_backends/pybullet/assets.py) so that a scenario means the same thing on both backends.
Frames: a vessel's origin is the centre of its base, a rod's its centre (long axis = z), an
oven's the centre of its floor, a button's the centre of its housing's base. SAPIEN primitives'
cylinder axis is x; `UP` turns it to z.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import sapien
import sapien.physx as physx

UP = [math.sqrt(0.5), 0.0, -math.sqrt(0.5), 0.0]  # wxyz: Ry(-90 deg), a primitive's x axis onto world z
RACK_HEIGHT = 0.06
DOOR_OPEN = math.radians(80)  # the planned open angle of the oven door
OVEN_DIMS = {"width": 0.24, "depth": 0.22, "height": 0.18}
HANDLE_OFFSET = (-0.035, OVEN_DIMS["width"] - 0.035)  # handle axis in the door frame (x, y)
BUTTON_DIMS = {"travel": 0.012, "top": 0.06}


def _mat(rgba) -> sapien.render.RenderMaterial:
    return sapien.render.RenderMaterial(base_color=[float(c) for c in rgba], roughness=0.6, specular=0.3)


@dataclass(frozen=True)
class VesselSpec:
    radius: float
    height: float
    rgba: tuple[float, float, float, float]
    neck_radius: float = 0.0  # > 0: a flask, the upper 40 % narrows to this radius
    mass: float = 0.12


def vessel(scene, name: str, spec: VesselSpec, pos) -> object:
    """Beaker, bottle or flask: a cylinder body (with a neck for a flask) and a dark disc for the mouth."""
    b = scene.create_actor_builder()
    r, h = spec.radius, spec.height
    body_h = 0.6 * h if spec.neck_radius > 0 else h
    glass = _mat(spec.rgba)
    b.add_cylinder_collision(sapien.Pose([0, 0, body_h / 2], UP), radius=r, half_length=body_h / 2)
    b.add_cylinder_visual(sapien.Pose([0, 0, body_h / 2], UP), radius=r, half_length=body_h / 2, material=glass)
    mouth_r = r * 0.85
    if spec.neck_radius > 0:
        nh = h - body_h
        b.add_cylinder_collision(sapien.Pose([0, 0, body_h + nh / 2], UP), radius=spec.neck_radius, half_length=nh / 2)
        b.add_cylinder_visual(
            sapien.Pose([0, 0, body_h + nh / 2], UP), radius=spec.neck_radius, half_length=nh / 2, material=glass
        )
        mouth_r = spec.neck_radius * 0.8
    b.add_cylinder_visual(
        sapien.Pose([0, 0, h + 0.0005], UP), radius=mouth_r, half_length=0.0008, material=_mat((0.12, 0.16, 0.2, 1))
    )
    b.set_mass_and_inertia(spec.mass, sapien.Pose([0, 0, body_h / 2]), _cylinder_inertia(spec.mass, r, h))
    b.initial_pose = sapien.Pose(list(pos))
    return b.build(name=name)


def _cylinder_inertia(m: float, r: float, h: float) -> list[float]:
    side = m * (3 * r * r + h * h) / 12
    return [side, side, 0.5 * m * r * r]


def rod(scene, name: str, pos, length: float, radius: float, rgba, mass: float = 0.03) -> object:
    """Glass rod or test tube: a cylinder along z, origin at its centre."""
    b = scene.create_actor_builder()
    b.add_cylinder_collision(sapien.Pose([0, 0, 0], UP), radius=radius, half_length=length / 2)
    b.add_cylinder_visual(sapien.Pose([0, 0, 0], UP), radius=radius, half_length=length / 2, material=_mat(rgba))
    b.set_mass_and_inertia(mass, sapien.Pose(), _cylinder_inertia(mass, radius, length))
    b.initial_pose = sapien.Pose(list(pos))
    return b.build(name=name)


def rack(
    scene, name: str, pos, holes: int = 3, pitch: float = 0.05, hole: float = 0.028, rgba=(0.55, 0.38, 0.22, 1.0)
) -> object:
    """Test-tube rack (fixed): a base plate, two end walls and a top plate with square holes along y (2.8 cm
    for a 1.8 cm tube: open-loop keyframes carry the few millimetres a grasp shifts the tube)."""
    t, height, depth = 0.006, RACK_HEIGHT, 0.05
    length = holes * pitch
    parts = [((depth / 2, length / 2, t / 2), (0, 0, t / 2))]
    for sgn in (-1, 1):  # end walls
        parts.append(((depth / 2, t / 2, height / 2), (0, sgn * (length / 2 - t / 2), height / 2)))
    rim = (depth - hole) / 4
    for sgn in (-1, 1):  # front and back bars of the top plate
        parts.append(((rim, length / 2, t / 2), (sgn * (hole / 2 + rim), 0, height - t / 2)))
    for i in range(holes + 1):  # separators between the holes
        y = -length / 2 + i * pitch
        parts.append(((hole / 2, (pitch - hole) / 2, t / 2), (0, y, height - t / 2)))
    b = scene.create_actor_builder()
    for he, lp in parts:
        b.add_box_collision(sapien.Pose(list(lp)), half_size=list(he))
        b.add_box_visual(sapien.Pose(list(lp)), half_size=list(he), material=_mat(rgba))
    b.initial_pose = sapien.Pose(list(pos))
    return b.build_kinematic(name=name)


def hole_positions(rack_pos, holes: int = 3, pitch: float = 0.05) -> list[tuple[float, float]]:
    length = holes * pitch
    return [(float(rack_pos[0]), float(rack_pos[1] - length / 2 + pitch * (i + 0.5))) for i in range(holes)]


def zone(scene, name: str, pos, radius: float = 0.05, rgba=(0.2, 0.8, 0.3, 1.0)) -> object:
    """A flat coloured target mark on the bench (visual only, no collision)."""
    b = scene.create_actor_builder()
    b.add_cylinder_visual(sapien.Pose([0, 0, 0], UP), radius=radius, half_length=0.0005, material=_mat(rgba))
    b.initial_pose = sapien.Pose([float(pos[0]), float(pos[1]), 0.0006])
    return b.build_kinematic(name=name)


def button(scene, name: str, pos, rgba=(0.85, 0.1, 0.1, 1.0)) -> object:
    """Push button: a fixed housing and a cap on a sprung prismatic joint (q = how far it is pressed)."""
    ab = scene.create_articulation_builder()
    base = ab.create_link_builder(None)
    base.set_name("housing")
    base.add_box_collision(sapien.Pose([0, 0, 0.02]), half_size=[0.04, 0.04, 0.02])
    base.add_box_visual(sapien.Pose([0, 0, 0.02]), half_size=[0.04, 0.04, 0.02], material=_mat((0.25, 0.25, 0.28, 1)))
    cap = ab.create_link_builder(base)
    cap.set_name("cap")
    cap.add_cylinder_collision(sapien.Pose([0, 0, 0], UP), radius=0.022, half_length=0.01)
    cap.add_cylinder_visual(sapien.Pose([0, 0, 0], UP), radius=0.022, half_length=0.01, material=_mat(rgba))
    cap.set_mass_and_inertia(0.05, sapien.Pose(), [1e-5, 1e-5, 1e-5])
    down = [math.sqrt(0.5), 0.0, math.sqrt(0.5), 0.0]  # Ry(+90 deg): the joint's x axis onto world -z
    cap.set_joint_name("press")
    cap.set_joint_properties(
        "prismatic",
        limits=[[0.0, BUTTON_DIMS["travel"]]],
        pose_in_parent=sapien.Pose([0, 0, BUTTON_DIMS["top"] - 0.01], down),
        pose_in_child=sapien.Pose([0, 0, 0], down),
        friction=0.0,
        damping=0.0,
    )
    ab.initial_pose = sapien.Pose(list(pos))
    art = ab.build(name=name, fix_root_link=True)
    j = art.active_joints[0]
    j.set_drive_properties(stiffness=300.0, damping=5.0)  # the spring that pushes the cap back up
    j.set_drive_target(0.0)
    return art


def oven(scene, name: str, pos, rgba=(0.88, 0.88, 0.86, 1.0), door_rgba=(0.55, 0.62, 0.68, 1.0)) -> object:
    """Drying oven: a fixed cabinet open towards the robot (-x), closed by a door hinged on a vertical
    axis at its front edge on the -y side, with a vertical handle near the free edge. q = door angle
    (0 closed, positive swings the free edge towards the robot)."""
    w, d, h, t = OVEN_DIMS["width"], OVEN_DIMS["depth"], OVEN_DIMS["height"], 0.01
    w2, d2 = w / 2, d / 2
    ab = scene.create_articulation_builder()
    body = ab.create_link_builder(None)
    body.set_name("cabinet")
    for he, lp in [
        ((d2, w2, t / 2), (0, 0, t / 2)),
        ((d2, w2, t / 2), (0, 0, h - t / 2)),
        ((t / 2, w2, h / 2), (d2 - t / 2, 0, h / 2)),
        ((d2, t / 2, h / 2), (0, -w2 + t / 2, h / 2)),
        ((d2, t / 2, h / 2), (0, w2 - t / 2, h / 2)),
    ]:
        body.add_box_collision(sapien.Pose(list(lp)), half_size=list(he))
        body.add_box_visual(sapien.Pose(list(lp)), half_size=list(he), material=_mat(rgba))
    door = ab.create_link_builder(body)
    door.set_name("door")
    hx, hy = HANDLE_OFFSET
    dark = _mat((0.2, 0.2, 0.2, 1))
    plate = sapien.Pose([-t / 2, w2, h / 2 + 0.003])
    door.add_box_collision(plate, half_size=[t / 2, w2, h / 2 - 0.004])
    door.add_box_visual(plate, half_size=[t / 2, w2, h / 2 - 0.004], material=_mat(door_rgba))
    grip = sapien.Pose([hx, hy, h / 2], UP)
    door.add_cylinder_collision(grip, radius=0.007, half_length=0.055)
    door.add_cylinder_visual(grip, radius=0.007, half_length=0.055, material=dark)
    for dz in (-0.045, 0.045):  # standoffs holding the handle
        sp = sapien.Pose([-0.018, hy, h / 2 + dz])
        door.add_box_collision(sp, half_size=[0.016, 0.006, 0.006])
        door.add_box_visual(sp, half_size=[0.016, 0.006, 0.006], material=dark)
    door.set_mass_and_inertia(0.5, sapien.Pose([-t / 2, w2, h / 2]), [0.005, 0.005, 0.005])
    vertical = [math.sqrt(0.5), 0.0, -math.sqrt(0.5), 0.0]  # the revolute joint's x axis onto world z
    door.set_joint_name("hinge")
    door.set_joint_properties(
        "revolute",
        limits=[[0.0, math.radians(100)]],
        pose_in_parent=sapien.Pose([-d2, -w2, 0.0], vertical),
        pose_in_child=sapien.Pose([0, 0, 0], vertical),
        friction=0.0,
        damping=0.0,
    )
    ab.initial_pose = sapien.Pose(list(pos))
    art = ab.build(name=name, fix_root_link=True)
    j = art.active_joints[0]
    # A force-limited damper holds the door where it is left (a real oven door does not swing on its own).
    j.set_drive_properties(stiffness=0.0, damping=2.0, force_limit=1.0)
    j.set_drive_velocity_target(0.0)
    return art


def handle_position(oven_pos, angle: float) -> np.ndarray:
    """World position of the door handle's centre at a door angle (to plan keyframes)."""
    d, w, h = OVEN_DIMS["depth"], OVEN_DIMS["width"], OVEN_DIMS["height"]
    hinge = np.array([oven_pos[0] - d / 2, oven_pos[1] - w / 2, oven_pos[2]])
    lx, ly = HANDLE_OFFSET
    c, s = math.cos(angle), math.sin(angle)
    return hinge + np.array([lx * c - ly * s, lx * s + ly * c, h / 2])


def set_color(obj, rgba) -> None:
    """Recolour every visual part of an actor or articulation link (unseen-object/scene variants)."""
    for ent in _entities(obj):
        comp = ent.find_component_by_type(sapien.render.RenderBodyComponent)
        if comp is None:
            continue
        for shape in comp.render_shapes:
            for part in shape.parts if hasattr(shape, "parts") else [shape]:
                mat = part.material
                mat.base_color = [float(c) for c in rgba]
                if hasattr(mat, "base_color_texture"):
                    mat.base_color_texture = None


def _entities(obj) -> list:
    if hasattr(obj, "links"):  # a ManiSkill Articulation
        return [ent for link in obj.links for ent in (c.entity for c in link._objs)]
    return list(obj._objs)


def friction_material(static: float, dynamic: float, restitution: float) -> physx.PhysxMaterial:
    """A fresh PhysX material: perturbations never edit a material that other shapes may share."""
    return physx.PhysxMaterial(static, dynamic, restitution)
