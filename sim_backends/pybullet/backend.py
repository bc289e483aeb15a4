"""PyBulletSource: the `FailureSource` implementation on PyBullet (DIRECT mode, CPU)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pybullet as p
from omegaconf import OmegaConf

from labrobfail_vlm.taxonomy import horizon_of
from sim_backends.labeler import derive_labels
from sim_backends.perturbations.physics import PhysicsEvent
from sim_backends.pybullet import assets, scene as scene_mod
from sim_backends.pybullet import templates  # noqa: F401 - registers the task templates
from sim_backends.pybullet.plan import Plan
from sim_backends.pybullet.render import Renderer, png_bytes
from sim_backends.pybullet.robot import DT
from sim_backends.registry import TASK_TEMPLATES, register_backend
from sim_backends.source import FailureSource
from sim_backends.types import Episode, Keyframe

TASKS_FILE = Path(__file__).resolve().parents[2] / "configs" / "tasks" / "pybullet.yaml"
TRACE_EVERY = 6  # physics steps per trace sample: 240 Hz / 6 = 40 Hz


def load_task_config(path: str | Path = TASKS_FILE) -> dict[str, Any]:
    cfg = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    assert isinstance(cfg, dict)
    for name, sc in cfg["scenarios"].items():
        if sc.get("template") not in TASK_TEMPLATES:
            raise ValueError(f"scenario {name}: unknown template {sc.get('template')!r}")
    return cfg


@register_backend("pybullet", image_size=224, cameras=["front", "side"], wrist=False, egl=False)
class PyBulletSource(FailureSource):
    name = "pybullet"

    def __init__(self, image_size: int = 224, cameras: Sequence[str] = ("front", "side"), wrist: bool = False,
                 egl: bool = False, render: bool = True, tasks_file: str | Path | None = None,
                 custom_objects: dict[str, dict[str, Any]] | None = None,
                 custom_scene: dict[str, Any] | None = None):
        self.cfg = load_task_config(tasks_file or TASKS_FILE)
        self.cid = p.connect(p.DIRECT)
        if egl:
            import pkgutil
            egl_mod = pkgutil.get_loader("eglRenderer")
            if egl_mod is None:
                raise ValueError("egl: the eglRenderer plugin is not available in this PyBullet build")
            p.loadPlugin(egl_mod.get_filename(), "_eglRendererPlugin", physicsClientId=self.cid)
        self.renderer = Renderer(self.cid, cameras, image_size, wrist=wrist, egl=egl) if render else None
        self.custom_objects = custom_objects
        self.custom_scene = custom_scene
        self.scene: scene_mod.Scene | None = None
        self.plan: Plan | None = None
        self._fresh = False
        self._key: tuple[str, int, str] = ("", 0, "")

    # -- FailureSource ------------------------------------------------------------------------------
    def scenarios(self) -> list[str]:
        return list(self.cfg["scenarios"])

    def scenario_info(self, scenario: str) -> dict[str, Any]:
        sc = self._scenario(scenario)
        tmpl = self.cfg["templates"].get(sc["template"], {})
        return {"template": sc["template"], "perturbations": sc.get("perturbations", tmpl.get("perturbations", [])),
                "substitutes": sc.get("substitutes", {})}

    def _scenario(self, scenario: str) -> dict[str, Any]:
        if scenario not in self.cfg["scenarios"]:
            raise ValueError(f"task: unknown scenario {scenario!r}")
        return self.cfg["scenarios"][scenario]

    def reset(self, scenario: str, seed: int, variant: str = "seen") -> None:
        if variant not in scene_mod.VARIANTS:
            raise ValueError(f"variant: unknown variant {variant!r}; expected one of {', '.join(scene_mod.VARIANTS)}")
        sc = self._scenario(scenario)
        cid = self.cid
        p.resetSimulation(physicsClientId=cid)
        p.setPhysicsEngineParameter(deterministicOverlappingPairs=1, numSolverIterations=50, fixedTimeStep=DT,
                                    physicsClientId=cid)
        p.setGravity(0, 0, -9.81, physicsClientId=cid)
        rng = np.random.default_rng(seed)
        self.scene = scene_mod.build(cid, sc["layout"], variant, rng, self.custom_objects, self.custom_scene)
        if self.renderer is not None:
            self.renderer.light = tuple(self.scene.appearance["light"])
        for _ in range(60):  # let liquid and glassware settle before anything is planned
            p.stepSimulation(physicsClientId=cid)
        self.plan = Plan(self.scene)
        TASK_TEMPLATES[sc["template"]].cls(self.plan, dict(sc.get("params", {})))
        self._fresh = True
        self._key = (scenario, seed, variant)

    def scripted_keyframes(self) -> list[Keyframe]:
        assert self.plan is not None, "reset() first"
        return list(self.plan.keyframes)

    def object_positions(self) -> dict[str, tuple[float, float, float]]:
        assert self.scene is not None, "reset() first"
        out = {k: tuple(v.home) for k, v in self.scene.objects.items()}
        out.update(self.scene.zones)
        return out

    def execute(self, keyframes: Sequence[Keyframe], physics_events: Sequence[PhysicsEvent] = ()) -> Episode:
        if not self._fresh or self.scene is None or self.plan is None:
            raise RuntimeError("execute() needs a fresh reset(): every episode starts from the seeded initial state")
        self._fresh = False
        scene, robot = self.scene, self.scene.robot
        trace = _Trace(scene)
        counter = [0]

        def step() -> None:
            p.stepSimulation(physicsClientId=self.cid)
            counter[0] += 1
            if counter[0] % TRACE_EVERY == 0:
                trace.sample(counter[0] * DT, kf_index[0])

        kf_index = [0]
        images: list[list[bytes]] = [[] for _ in (self.renderer.views if self.renderer else [])]
        trace.sample(0.0, 0)
        for i, kf in enumerate(keyframes):
            kf_index[0] = i
            for ev in physics_events:
                if ev.at_keyframe == i:
                    self._apply_physics(ev)
            robot.set_gripper(kf.gripper)
            robot.move_to(kf.pos, kf.quat, kf.speed, step, settle_steps=kf.settle_steps)
            trace.sample(counter[0] * DT, i)
            trace.kf_end.append(len(trace.cols["t"]) - 1)
            if self.renderer is not None:
                for v, img in enumerate(self.renderer.render(robot.id)):
                    images[v].append(png_bytes(img))
        # Let things come to rest so that final-state goals are judged on a settled scene.
        for _ in range(90):
            step()
        meta = self._task_meta(keyframes)
        data = trace.to_dict()
        labels = derive_labels(data, meta)
        scenario, seed, variant = self._key
        return Episode(
            episode_id="", backend=self.name, task=self._scenario(scenario)["template"], scenario=scenario,
            variant=variant, seed=seed, pair_id="", role="", actions=self.plan.actions,
            horizon=horizon_of(len(self.plan.keyframes)), nominal_keyframes=list(self.plan.keyframes),
            executed_keyframes=list(keyframes), camera_names=list(self.renderer.views if self.renderer else []),
            images=images, state_trace=data, labels=labels, task_meta=meta)

    def close(self) -> None:
        if self.cid is not None and p.isConnected(self.cid):
            p.disconnect(self.cid)
        self.cid = None  # type: ignore[assignment]

    # -- helpers -------------------------------------------------------------------------------------
    def _apply_physics(self, ev: PhysicsEvent) -> None:
        scene, cid = self.scene, self.cid
        assert scene is not None
        if ev.param == "grip_force":
            scene.robot.grip_force *= ev.scale
            scene.robot.set_gripper(scene.robot.gripper_cmd)
            return
        if ev.param in ("liquid_viscosity", "liquid_mass"):
            for b in scene.particles.get(ev.target, []):
                if ev.param == "liquid_mass":
                    m = p.getDynamicsInfo(b, -1, physicsClientId=cid)[0]
                    p.changeDynamics(b, -1, mass=m * ev.scale, physicsClientId=cid)
                else:
                    p.changeDynamics(b, -1, linearDamping=assets.LIQUID_DAMPING * ev.scale, physicsClientId=cid)
            return
        body = scene.body(ev.target)
        info = p.getDynamicsInfo(body, -1, physicsClientId=cid)
        if ev.param == "friction":
            p.changeDynamics(body, -1, lateralFriction=info[1] * ev.scale, physicsClientId=cid)
        elif ev.param == "mass":
            p.changeDynamics(body, -1, mass=info[0] * ev.scale, physicsClientId=cid)

    def _task_meta(self, executed: Sequence[Keyframe]) -> dict[str, Any]:
        scene, plan = self.scene, self.plan
        assert scene is not None and plan is not None
        places = {k: list(v) for k, v in self.object_positions().items()}
        return {
            "steps": plan.steps,
            "goals": plan.goals,
            "objects": {k: {"kind": o.kind, "dims": o.dims, "home": list(o.home)} for k, o in scene.objects.items()},
            "places": places,
            "nominal": [{"name": k.name, "pos": list(k.pos), "quat": list(k.quat), "gripper": k.gripper,
                         "segment": k.segment} for k in plan.keyframes],
            "executed": [k.name for k in executed],
            "bench_top": assets.BENCH_TOP,
            "liquid_total": {k: len(v) for k, v in scene.particles.items()},
            "labels": scene.labels,
            "description": self._describe(),
        }

    def _describe(self) -> str:
        """The task in words (the `{task_name}` of the VQA preamble), from the template's description."""
        assert self.scene is not None
        sc = self._scenario(self._key[0])
        text = sc.get("description") or self.cfg["templates"].get(sc["template"], {}).get("description")
        return str(text or self._key[0].replace("_", " ")).format_map({**self.scene.labels, **sc.get("params", {})})


class _Trace:
    """Samples the simulator state into columns (lists) at 40 Hz."""

    def __init__(self, scene: scene_mod.Scene):
        self.scene = scene
        self.cols: dict[str, list] = {"t": [], "kf": [], "ee_pos": [], "ee_quat": [], "width": [], "grip_cmd": []}
        self.kf_end: list[int] = []
        self.movables = {k: o for k, o in scene.objects.items() if o.kind in ("vessel", "rod")}
        self.vessels = {k: o for k, o in scene.objects.items() if o.kind == "vessel"}
        self.all_particles = [b for ids in scene.particles.values() for b in ids]

    def sample(self, t: float, kf: int) -> None:
        sc, cid, c = self.scene, self.scene.cid, self.cols
        r = lambda v: [round(float(x), 4) for x in v]  # noqa: E731
        pos, quat = sc.robot.ee_pose()
        c["t"].append(round(t, 4)); c["kf"].append(kf)
        c["ee_pos"].append(r(pos)); c["ee_quat"].append(r(quat))
        c["width"].append(round(sc.robot.finger_width(), 4)); c["grip_cmd"].append(sc.robot.gripper_cmd)
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
            free = 0
            for q in pts:
                hit = None
                for name, o in self.vessels.items():
                    bp, bq = p.getBasePositionAndOrientation(o.body, physicsClientId=cid)
                    inv = p.invertTransform(bp, bq)
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

    def to_dict(self) -> dict[str, list]:
        return {**self.cols, "kf_end": self.kf_end}
