"""ManiSkillSource: the `FailureSource` implementation on ManiSkill3 / SAPIEN (PhysX).

One ManiSkill environment per environment id is built on first use and kept; every `reset`
reconfigures it (a fresh PhysX scene: same seed, same episode) after undoing the physics
perturbations of the previous episode explicitly, since values set through the SAPIEN API (a
shared PhysX material above all) outlive `env.reset()`.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from mani_skill import logger as ms_logger

from labrobfail_vlm.config import CONFIG_DIR
from sim_backends.maniskill import (
    assets,
    envs,
    templates,  # noqa: F401 - registers the task templates
    vulkan_problem,  # first: offline defaults before mani_skill is imported
)
from sim_backends.maniskill.plan import Plan, SceneView, Thing
from sim_backends.maniskill.robot import Arm, Contacts, canonical_quat, wxyz_to_xyzw
from sim_backends.maniskill.scene_spec import scene_spec
from sim_backends.perturbations.physics import PhysicsEvent
from sim_backends.registry import register_backend, task_templates
from sim_backends.scenario_config import ScenarioConfig
from sim_backends.schema import MOVABLE, NominalKeyframe, ObjectInfo, TaskMeta
from sim_backends.source import FailureSource
from sim_backends.types import Keyframe

ms_logger.setLevel(logging.ERROR)  # ManiSkill warns about missing CUDA on every CPU machine
TASKS_FILE = CONFIG_DIR / "tasks" / "maniskill.yaml"
SETTLE_STEPS = 20  # control steps after the last keyframe (1 s at ManiSkill's 20 Hz)
PRE_STEPS = 3  # control steps holding the start pose after a reset, before the plan reads the scene
SIM_BACKENDS = {"cpu": ("physx_cpu", "cpu"), "gpu": ("physx_cuda", "gpu")}


@register_backend("maniskill", image_size=224, cameras=["front", "side"], wrist=False, sim_backend="cpu")
class ManiSkillSource(ScenarioConfig, FailureSource):
    name = "maniskill"
    TASKS_FILE = TASKS_FILE
    CAMERAS = envs.CAMERAS

    def __init__(
        self,
        image_size: int = 224,
        cameras: Sequence[str] = ("front", "side"),
        wrist: bool = False,
        sim_backend: str = "cpu",
        render: bool = True,
        tasks_file: str | Path | None = None,
    ):
        super().__init__()
        self.cfg = self.load_task_config(tasks_file)
        self.check_cameras(cameras)
        self.views = list(cameras) + ([envs.WRIST] if wrist else [])
        self.image_size = int(image_size)
        self.render_on = bool(render) and bool(self.views)
        self.sim_backend = self.prepare_kwargs({"sim_backend": sim_backend})["sim_backend"]
        self._envs: dict[str, Any] = {}
        self.env = None
        self.arm: Arm | None = None
        self.plan: Plan | None = None
        self.info: envs.LrfScene | None = None
        self._undo: list[tuple[Any, ...]] = []
        self._cols: dict[str, list] = {}
        self._kf_end: list[int] = []
        self._steps = 0
        self._contacts: Contacts | None = None

    # -- configuration (no simulator needed) ----------------------------------------------------------
    @classmethod
    def prepare_kwargs(cls, kwargs: dict[str, Any]) -> dict[str, Any]:
        """The maniskill section of `backend_kwargs`: wrist (bool), sim_backend (cpu | gpu)."""
        out = dict(kwargs)
        sb = out.get("sim_backend", "cpu")
        if sb not in SIM_BACKENDS:
            raise ValueError(f"sim_backend: must be one of {', '.join(SIM_BACKENDS)}, got {sb!r}")
        if sb == "gpu":
            import torch

            if not torch.cuda.is_available():
                raise ValueError("sim_backend: gpu needs a CUDA device and none was found")
        if not isinstance(out.get("wrist", False), bool):
            raise ValueError(f"wrist: must be true or false, got {out.get('wrist')!r}")
        return out

    @classmethod
    def unavailable(cls) -> str | None:
        """ManiSkill needs a Vulkan device even without cameras (sim_backends.maniskill.vulkan_problem)."""
        return vulkan_problem()

    @classmethod
    def check_scenario(cls, name: str, sc: dict[str, Any]) -> None:
        if sc.get("env") not in envs.ENVS:
            try:
                envs.check_offline(str(sc.get("env")))
            except ValueError as e:
                raise ValueError(f"scenario {name}: {e}") from None
            raise ValueError(
                f"scenario {name}: env {sc.get('env')!r} is not wrapped for LabRobFail; wrapped: {', '.join(envs.ENVS)}"
            )

    @property
    def camera_names(self) -> list[str]:
        return list(self.views) if self.render_on else []

    def _env(self, env_id: str):
        if env_id not in self._envs:
            envs.check_offline(env_id)
            sim, rend = SIM_BACKENDS[self.sim_backend]
            try:
                self._envs[env_id] = envs.ENVS[env_id](
                    obs_mode="none",
                    reward_mode="none",
                    control_mode="pd_joint_pos",
                    sim_backend=sim,
                    render_backend=rend if self.render_on else "none",
                    lrf_views=tuple(self.views),
                    lrf_image_size=self.image_size,
                )
            except RuntimeError as e:
                raise ValueError(f"env: ManiSkill could not build {env_id} ({str(e).splitlines()[0]})") from None
        return self._envs[env_id]

    def _reset(self, scenario: str, seed: int, variant: str) -> None:
        sc = self._scenario(scenario)
        self._restore()
        rng = np.random.default_rng(seed)
        spec = scene_spec(self.cfg, sc, variant, rng)
        env = self.env = self._env(sc["env"])
        env.reset(seed=int(seed) % (2**31), options={"reconfigure": True, "lrf": spec})
        self.arm = Arm(env)
        for _ in range(PRE_STEPS):  # let anything placed exactly on the table come to rest
            self.arm.hold()
        self.info = env.lrf_objects()
        self.info.labels = {
            **{r: o.label for r, o in self.info.objects.items()},
            **self.info.labels,
            **spec.get("labels", {}),
        }
        self.plan = Plan(self._view())
        task_templates(self.name)[sc["template"]].cls(self.plan, dict(sc.get("params", {})))

    def _view(self) -> SceneView:
        things = {}
        for role, o in self.info.objects.items():
            pos, _, body = self._pose(o)
            things[role] = Thing(o.kind, pos, dict(o.dims), body)
        extra: dict[str, Any] = {}
        if hasattr(self.env, "goal_pose") and isinstance(self.env, envs.LrfPegInsertionSide):
            g = self.env.goal_pose
            extra = {"peg_goal_p": g.p[0].cpu().numpy().tolist(), "peg_goal_q": wxyz_to_xyzw(g.q[0].cpu().numpy())}
        return SceneView(things, dict(self.info.zones), extra)

    @staticmethod
    def _pose(o: envs.TaskObject) -> tuple[np.ndarray, tuple, tuple]:
        pose = o.handle.pose if hasattr(o.handle, "pose") else o.handle.root.pose
        body = wxyz_to_xyzw(pose.q[0].cpu().numpy())
        return (
            pose.p[0].cpu().numpy().astype(float),
            canonical_quat(body, o.frame if o.kind in MOVABLE else "body"),
            body,
        )

    def scripted_keyframes(self) -> list[Keyframe]:
        assert self.plan is not None, "reset() first"
        return list(self.plan.keyframes)

    def object_positions(self) -> dict[str, tuple[float, float, float]]:
        assert self.plan is not None, "reset() first"
        out = {k: tuple(float(v) for v in t.pos) for k, t in self.plan.scene.objects.items()}
        out.update({k: tuple(float(v) for v in z) for k, z in self.plan.scene.zones.items()})
        return out

    # -- stepping primitives --------------------------------------------------------------------------
    def _begin(self) -> None:
        self._cols = {"t": [], "kf": [], "ee_pos": [], "ee_quat": [], "width": [], "grip_cmd": []}
        self._kf_end = []
        self._steps = 0
        movable = {r: o.handle for r, o in self.info.objects.items() if o.kind in MOVABLE}
        self._contacts = Contacts(self.env, movable)
        self._sample(0)

    def _sample(self, kf: int) -> None:
        c, arm = self._cols, self.arm
        r = lambda v: [round(float(x), 4) for x in v]  # noqa: E731
        pos, quat = arm.tcp()
        c["t"].append(round(self._steps * arm.dt, 4))
        c["kf"].append(kf)
        c["ee_pos"].append(r(pos))
        c["ee_quat"].append(r(quat))
        c["width"].append(round(arm.width(), 4))
        c["grip_cmd"].append(arm.grip)
        touching = self._contacts.count()
        for role, o in self.info.objects.items():
            if o.kind in MOVABLE:
                p, q, _ = self._pose(o)
                c.setdefault(f"{role}.pos", []).append(r(p))
                c.setdefault(f"{role}.quat", []).append(r(q))
                c.setdefault(f"{role}.contacts", []).append(touching.get(role, 0))
            elif o.kind in ("oven", "button"):
                c.setdefault(f"{role}.q", []).append(round(float(o.handle.get_qpos()[0, 0]), 4))

    def _tick(self, kf: int) -> None:
        self._steps += 1
        self._sample(kf)

    def _move(self, kf: Keyframe, index: int) -> None:
        self.arm.move_to(
            kf.pos,
            kf.quat,
            kf.gripper,
            kf.speed,
            lambda: self._tick(index),
            settle=kf.settle_steps,
            joint_space=kf.name in self.plan.joint_space,
        )
        self._kf_end.append(len(self._cols["t"]) - 1)

    def _settle(self) -> None:
        last = max(0, len(self._kf_end) - 1)  # samples keep the last keyframe's program counter
        for _ in range(SETTLE_STEPS):
            self.arm.hold()
            self._tick(last)

    def render(self) -> list[np.ndarray]:
        if not self.render_on:
            return []
        scene = self.env.scene
        scene.update_render(update_sensors=False, update_human_render_cameras=True)
        imgs = scene.get_human_render_camera_images()
        return [np.ascontiguousarray(imgs[v][0].cpu().numpy()[..., :3]) for v in self.views]

    def trace_so_far(self) -> dict[str, Any]:
        return {
            **{k: list(v) for k, v in self._cols.items()},
            "kf_end": list(self._kf_end),
            "rate_hz": float(self.env.control_freq),
        }

    # -- physics perturbations (Phi_phy) and their explicit undo --------------------------------------
    def _apply_physics(self, ev: PhysicsEvent) -> None:
        if ev.param == "grip_force":
            for j in self.env.agent.robot.active_joints[-2:]:
                for pj in j._objs:
                    self._undo.append(("drive", pj, pj.stiffness, pj.damping, pj.force_limit))
                    pj.set_drive_properties(
                        pj.stiffness * ev.scale, pj.damping * ev.scale, pj.force_limit * ev.scale, pj.drive_mode
                    )
            return
        if ev.target not in self.info.objects or self.info.objects[ev.target].kind not in MOVABLE:
            raise ValueError(f"physics perturbation: {ev.param} of {ev.target!r}: no such movable object")
        for body in self.info.objects[ev.target].handle._bodies:
            if ev.param == "mass":
                self._undo.append(("mass", body, body.mass))
                body.set_mass(body.mass * ev.scale)
            elif ev.param == "friction":
                for shape in body.collision_shapes:
                    m = shape.physical_material
                    self._undo.append(("material", shape, m))
                    # A fresh material: the shape's own is often PhysX's default, shared by every shape.
                    shape.set_physical_material(
                        assets.friction_material(
                            m.static_friction * ev.scale, m.dynamic_friction * ev.scale, m.restitution
                        )
                    )
            else:
                raise ValueError(f"physics perturbation: {ev.param!r} is not supported by the maniskill backend")

    def _restore(self) -> None:
        """Undo every physics perturbation of the last episode, newest first."""
        while self._undo:
            kind, obj, *old = self._undo.pop()
            if kind == "drive":
                obj.set_drive_properties(old[0], old[1], old[2], obj.drive_mode)
            elif kind == "mass":
                obj.set_mass(old[0])
            else:
                obj.set_physical_material(old[0])

    # -- task metadata --------------------------------------------------------------------------------
    def task_meta(self, executed: Sequence[Keyframe]) -> TaskMeta:
        plan = self.plan
        objects = {
            r: ObjectInfo(
                o.kind, {k: float(v) for k, v in o.dims.items()}, [float(v) for v in plan.scene.objects[r].pos]
            )
            for r, o in self.info.objects.items()
        }
        return TaskMeta(
            steps=plan.steps,
            goals=plan.goals,
            objects=objects,
            places={k: list(v) for k, v in self.object_positions().items()},
            nominal=[NominalKeyframe(k.name, list(k.pos), list(k.quat), k.gripper, k.segment) for k in plan.keyframes],
            executed=[k.name for k in executed],
            bench_top=0.0,
            liquid_total={},
            labels=dict(self.info.labels),
            description=self.describe(self._key[0], self.info.labels),
            robot_base=list(envs.ROBOT_BASE),
        )

    def close(self) -> None:
        self._undo.clear()
        for env in self._envs.values():
            env.close()
        self._envs.clear()
        self.env = None
