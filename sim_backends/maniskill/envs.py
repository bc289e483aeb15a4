"""ManiSkill environments for LabRobFail: stock Panda tabletop tasks wrapped, and a lab bench built in code.

Every environment here renders the LabRobFail views (front, side; optional wrist) as ManiSkill
"human render cameras", takes its appearance (bench and floor colour, light) and object colours
from the `lrf` entry of `reset(options=...)`, and describes its task objects through
`lrf_objects()` so that the backend can trace them. The stock task classes keep their own
geometry and randomisation (seeded by `reset(seed=...)`); the hooks below only add what
LabRobFail needs: a target mark on the table for PickCube, a minimum distance between object and
target, and recolouring for the unseen variants.

World frame: ManiSkill's table top is z = 0 and the Panda stands at x = -0.615.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import sapien
import torch
from mani_skill.envs.sapien_env import BaseEnv
from mani_skill.envs.tasks.tabletop.lift_peg_upright import LiftPegUprightEnv
from mani_skill.envs.tasks.tabletop.peg_insertion_side import PegInsertionSideEnv
from mani_skill.envs.tasks.tabletop.pick_cube import PickCubeEnv
from mani_skill.envs.tasks.tabletop.pull_cube import PullCubeEnv
from mani_skill.envs.tasks.tabletop.push_cube import PushCubeEnv
from mani_skill.envs.tasks.tabletop.stack_cube import StackCubeEnv
from mani_skill.sensors.camera import CameraConfig
from mani_skill.utils import sapien_utils
from mani_skill.utils.scene_builder.table import TableSceneBuilder
from mani_skill.utils.structs.pose import Pose

from sim_backends.maniskill import assets
from sim_backends.schema import MOVABLE
from sim_backends.types import WRIST

ROBOT_BASE = (-0.615, 0.0, 0.0)
# eye, target, vertical field of view (deg), framed on the workspace (x -0.25..0.2, |y| < 0.35).
CAMERAS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float], float]] = {
    "front": ((0.32, 0.30, 0.42), (-0.10, 0.0, 0.05), 55.0),
    "side": ((-0.08, -0.66, 0.36), (-0.08, 0.0, 0.07), 55.0),
}


@dataclass
class TaskObject:
    """A task object as the backend traces it.

    frame: how its recorded pose is read. "body": as built (vessel origin at the base centre, rod
    long axis = z); "cube": a cube is symmetric, so the recorded frame is the one whose z axis
    points up; "x_axis": a peg whose long axis is the body's x axis (recorded with z along it)."""

    handle: Any  # ManiSkill Actor or Articulation
    kind: str  # vessel | rod | oven | button | rack (sim_backends/schema.py ObjectInfo.kind)
    dims: dict[str, float]
    label: str
    frame: str = "body"


@dataclass
class LrfScene:
    objects: dict[str, TaskObject] = field(default_factory=dict)
    zones: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    labels: dict[str, str] = field(default_factory=dict)


class LabRobFailEnv:
    """Mixin (first base) for a ManiSkill task: LabRobFail cameras, appearance and `lrf_objects`."""

    def __init__(self, *args, lrf_views: tuple[str, ...] = ("front", "side"), lrf_image_size: int = 224, **kwargs):
        self._lrf_views = tuple(lrf_views)
        self._lrf_size = int(lrf_image_size)
        self._lrf: dict[str, Any] = {}
        self.lrf = LrfScene()
        super().__init__(*args, **kwargs)

    @property
    def _default_sensor_configs(self):
        return []  # no observation cameras: LabRobFail renders its own views at keyframes

    @property
    def _default_human_render_camera_configs(self):
        out = []
        for v in self._lrf_views:
            if v == WRIST:
                # behind the fingers, looking along the approach axis, the hand's x axis up
                out.append(
                    CameraConfig(
                        v,
                        sapien.Pose([0.04, 0, -0.10], [0.7071068, 0, -0.7071068, 0]),
                        self._lrf_size,
                        self._lrf_size,
                        np.deg2rad(70),
                        0.01,
                        10,
                        mount=self.agent.tcp,
                    )
                )
                continue
            eye, target, fov = CAMERAS[v]
            out.append(
                CameraConfig(
                    v, sapien_utils.look_at(eye, target), self._lrf_size, self._lrf_size, np.deg2rad(fov), 0.01, 10
                )
            )
        return out

    def _load_agent(self, options: dict):
        BaseEnv._load_agent(self, options, sapien.Pose(p=list(ROBOT_BASE)))

    def _load_lighting(self, options: dict):
        app = self._lrf.get("appearance", {})
        self.scene.set_ambient_light([float(app.get("ambient", 0.3))] * 3)
        self.scene.add_directional_light(list(app.get("light", [1, 1, -1])), [1, 1, 1], shadow=False)
        self.scene.add_directional_light([0, 0, -1], [0.7, 0.7, 0.7])

    def reset(self, seed=None, options=None):
        options = dict(options or {})
        if "lrf" in options:
            self._lrf = dict(options["lrf"])
        return super().reset(seed=seed, options=options)

    def _load_scene(self, options: dict):
        super()._load_scene(options)
        app = self._lrf.get("appearance", {})
        ts = getattr(self, "table_scene", None)
        if ts is not None and app.get("bench") is not None:
            assets.set_color(ts.table, app["bench"])
        if ts is not None and app.get("floor") is not None:
            assets.set_color(ts.ground, app["floor"])
        self.lrf = self._lrf_scene()
        for role, rgba in self._lrf.get("colors", {}).items():
            assets.set_color(self.lrf.objects[role].handle, rgba)

    def _initialize_episode(self, env_idx: torch.Tensor, options: dict):
        super()._initialize_episode(env_idx, options)
        with torch.device(self.device):  # new tensors on the simulation's device (GPU sim)
            self._lrf_after_init()

    # -- per task ------------------------------------------------------------------------------------
    def _lrf_scene(self) -> LrfScene:
        raise NotImplementedError

    def _lrf_after_init(self) -> None:
        pass

    def lrf_objects(self) -> LrfScene:
        return self.lrf


def _cube(handle, half: float, label: str) -> TaskObject:
    return TaskObject(handle, "vessel", {"radius": half, "height": 2 * half, "neck": 0.0}, label, "cube")


def _far_target(env, obj_xy: np.ndarray, lo, hi, min_dist: float) -> np.ndarray:
    """A target position in the box [lo, hi] at least `min_dist` from the object (seeded episode RNG)."""
    xy = obj_xy
    for _ in range(200):
        xy = env._episode_rng.uniform(lo, hi)
        if np.linalg.norm(xy - obj_xy) >= min_dist:
            break
    return xy


class LrfPickCube(LabRobFailEnv, PickCubeEnv):
    """PickCube: pick the red cube and place it on a target mark on the table (the stock goal's xy)."""

    def _load_scene(self, options: dict):
        self.lrf_target = assets.zone(self.scene, "lrf_target", (0, 0, 0), radius=0.035, rgba=(0.2, 0.75, 0.3, 1))
        super()._load_scene(options)
        if self.scene.can_render():
            self.goal_site.hide_visual()  # the stock goal floats in the air; LabRobFail places on the table

    def _lrf_scene(self) -> LrfScene:
        return LrfScene({"obj": _cube(self.cube, self.cube_half_size, "red cube")}, labels={"target": "green mark"})

    def _lrf_after_init(self) -> None:
        cube = self.cube.pose.p[0].cpu().numpy()
        xy = _far_target(self, cube[:2], [-0.12, -0.2], [0.12, 0.2], 0.12)
        self.lrf_target.set_pose(Pose.create_from_pq(p=[float(xy[0]), float(xy[1]), 0.0006]))
        self.lrf.zones["target"] = (float(xy[0]), float(xy[1]), 0.0)


class LrfStackCube(LabRobFailEnv, StackCubeEnv):
    """StackCube: put the red cube on top of the green one."""

    def _lrf_scene(self) -> LrfScene:
        return LrfScene({"obj": _cube(self.cubeA, 0.02, "red cube"), "base": _cube(self.cubeB, 0.02, "green cube")})


class _PushLike(LabRobFailEnv):
    """PushCube / PullCube: move the cube onto the red and white target without grasping it."""

    def _lrf_scene(self) -> LrfScene:
        return LrfScene({"obj": _cube(self.obj, self.cube_half_size, "blue cube")}, labels={"target": "target"})

    def _lrf_after_init(self) -> None:
        p = self.goal_region.pose.p[0].cpu().numpy()
        self.lrf.zones["target"] = (float(p[0]), float(p[1]), 0.0)


class LrfPushCube(_PushLike, PushCubeEnv):
    pass


class LrfPullCube(_PushLike, PullCubeEnv):
    pass


class LrfLiftPegUpright(LabRobFailEnv, LiftPegUprightEnv):
    """LiftPegUpright: pick up the peg lying on the table and stand it upright."""

    def _lrf_scene(self) -> LrfScene:
        return LrfScene(
            {
                "peg": TaskObject(
                    self.peg,
                    "rod",
                    {"length": 2 * self.peg_half_length, "radius": self.peg_half_width},
                    "peg",
                    "x_axis",
                )
            }
        )


class LrfPegInsertionSide(LabRobFailEnv, PegInsertionSideEnv):
    """PegInsertionSide: insert the peg's orange end sideways into the hole of the yellow box."""

    def _lrf_scene(self) -> LrfScene:
        half = self.peg_half_sizes[0].cpu().numpy()
        return LrfScene(
            {
                "peg": TaskObject(
                    self.peg, "rod", {"length": 2 * float(half[0]), "radius": float(half[1])}, "peg", "x_axis"
                ),
                "box": TaskObject(self.box, "rack", {"height": 2 * float(half[0])}, "box with a hole"),
            }
        )

    def _lrf_after_init(self) -> None:
        goal = self.goal_pose  # the peg pose with its head at the hole's centre
        self.lrf.zones["hole"] = tuple(float(v) for v in goal.p[0].cpu().numpy())


class LabBenchEnv(LabRobFailEnv, BaseEnv):
    """A lab bench built from a layout: glassware, rods, a rack, a button, an oven, target zones.

    The layout (role -> build spec with world positions) comes in `reset(options={"lrf": {"layout":
    ...}})`; the backend draws it from the episode seed, so the environment itself is not random
    (the robot's start pose noise comes from ManiSkill's seeded episode RNG, as in the stock tasks).
    """

    SUPPORTED_ROBOTS = ["panda"]

    def __init__(self, *args, robot_uids="panda", **kwargs):
        super().__init__(*args, robot_uids=robot_uids, **kwargs)

    def _load_scene(self, options: dict):
        self.table_scene = TableSceneBuilder(self, robot_init_qpos_noise=0.02)
        self.table_scene.build()
        self._built: dict[str, Any] = {}
        self._zones: dict[str, tuple[float, float, float]] = {}
        for role, sp in self._lrf.get("layout", {}).items():
            kind, pos = sp["kind"], sp["pos"]
            if kind == "zone":
                assets.zone(
                    self.scene, role, pos, radius=sp.get("radius", 0.05), rgba=sp.get("rgba", (0.2, 0.8, 0.3, 1))
                )
                self._zones[role] = tuple(pos)
            elif kind == "vessel":
                vs = assets.VesselSpec(sp["radius"], sp["height"], tuple(sp["rgba"]), sp.get("neck_radius", 0.0))
                self._built[role] = assets.vessel(self.scene, role, vs, pos)
            elif kind == "rod":
                self._built[role] = assets.rod(self.scene, role, pos, sp["length"], sp["radius"], sp["rgba"])
            elif kind == "rack":
                self._built[role] = assets.rack(self.scene, role, pos)
                for i, h in enumerate(assets.hole_positions(pos)):
                    self._zones[f"{role}_hole{i}"] = (h[0], h[1], 0.0)
            elif kind == "button":
                self._built[role] = assets.button(self.scene, role, pos, rgba=sp.get("rgba", (0.85, 0.1, 0.1, 1)))
            elif kind == "oven":
                self._built[role] = assets.oven(self.scene, role, pos)
            else:
                raise ValueError(f"scenario: unknown object kind {kind!r}")
        super()._load_scene(options)

    def _lrf_scene(self) -> LrfScene:
        out = LrfScene(zones=dict(self._zones))
        for role, sp in self._lrf.get("layout", {}).items():
            if role in self._built:
                out.objects[role] = TaskObject(self._built[role], sp["kind"], dict(sp.get("dims", {})), sp["label"])
        return out

    def _initialize_episode(self, env_idx: torch.Tensor, options: dict):
        with torch.device(self.device):  # new tensors on the simulation's device (GPU sim)
            self._place_layout(env_idx)

    def _place_layout(self, env_idx: torch.Tensor) -> None:
        self.table_scene.initialize(env_idx)
        for role, sp in self._lrf.get("layout", {}).items():
            obj = self._built.get(role)
            if obj is None:
                continue
            if sp["kind"] in MOVABLE:
                obj.set_pose(Pose.create_from_pq(p=list(sp["pos"])))
                obj.set_linear_velocity(torch.zeros(3))
                obj.set_angular_velocity(torch.zeros(3))
            elif sp["kind"] in ("oven", "button"):
                obj.set_qpos(torch.tensor([[float(sp.get("open_angle", 0.0))]]))
                obj.set_qvel(torch.zeros((1, 1)))
        self._lrf_after_init()


# ManiSkill environment id -> the LabRobFail class that wraps it (configs/tasks/maniskill.yaml `env`).
ENVS: dict[str, type] = {
    "PickCube-v1": LrfPickCube,
    "StackCube-v1": LrfStackCube,
    "PushCube-v1": LrfPushCube,
    "PullCube-v1": LrfPullCube,
    "LiftPegUpright-v1": LrfLiftPegUpright,
    "PegInsertionSide-v1": LrfPegInsertionSide,
    "LabBench": LabBenchEnv,
}


def check_offline(env_id: str) -> None:
    """Refuse, in one line, an environment whose assets would have to be downloaded."""
    from mani_skill.utils import assets as ms_assets
    from mani_skill.utils.registration import REGISTERED_ENVS

    spec = REGISTERED_ENVS.get(env_id)
    if spec is None:
        return
    missing = []
    for aid in spec.asset_download_ids or []:
        ids = (
            ms_assets.expand_data_group_into_individual_data_source_ids(aid) if aid in ms_assets.DATA_GROUPS else [aid]
        )
        missing += [i for i in ids if i in ms_assets.DATA_SOURCES and not ms_assets.is_data_source_downloaded(i)]
    if missing:
        raise ValueError(
            f"env: ManiSkill environment {env_id} needs assets that are not in MS_ASSET_DIR "
            f"({', '.join(missing[:3])}{', ...' if len(missing) > 3 else ''}); downloads are off"
        )
