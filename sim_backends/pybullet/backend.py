"""PyBulletSource: the `FailureSource` implementation on PyBullet (DIRECT mode, CPU)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pybullet as p
from omegaconf import OmegaConf

from labrobfail_vlm.config import CONFIG_DIR, is_int
from sim_backends.goals import GOALS
from sim_backends.labeler import BREAK_SPEED, impact_speed
from sim_backends.perturbations.physics import PhysicsEvent
from sim_backends.pybullet import (
    assets,
    templates,  # noqa: F401 - registers the task templates
)
from sim_backends.pybullet import scene as scene_mod
from sim_backends.pybullet.plan import Plan
from sim_backends.pybullet.render import CAMERAS, Renderer
from sim_backends.pybullet.robot import DT
from sim_backends.pybullet.trace import TRACE_EVERY, TRACE_RATE_HZ, Rewinder, Trace
from sim_backends.registry import register_backend, task_templates
from sim_backends.scenario_config import ScenarioConfig
from sim_backends.schema import MOVABLE, NominalKeyframe, ObjectInfo, TaskMeta
from sim_backends.source import FailureSource
from sim_backends.types import Keyframe

TASKS_FILE = CONFIG_DIR / "tasks" / "pybullet.yaml"
# The solver stops early once its residual is below this (PyBullet's default 1e-7 runs all 50 iterations on
# resting contacts): a third less time per step with the same nominal success (measured over all scenarios).
SOLVER_RESIDUAL = 1e-3
LANDED = 0.05  # m/s: glassware whose base moves slower than this has come to rest (broken_glass)


@dataclass(frozen=True)
class Physics:
    """A `backend_kwargs.physics` preset."""

    solver_iterations: int = 50  # contact solver iterations per physics step (20 drops half the grasps)
    torsional_friction: bool = True  # False: every link's spinning and rolling friction 0 once the scene is built
    # True: an injected run continues from its nominal run's saved state at the first keyframe they differ in
    # (sim_backends/prefix.py); PyBullet's restoreState brings back positions and velocities exactly but not the joint
    # motors' last applied torques, so the continuation differs a little from a fresh run's
    reuse_prefix: bool = False


# `reference` (default): every dataset so far (a run.json without the key reads as it). `fast`: no spinning or
# rolling friction, about 14 % fewer instructions, the only setting of seven tried that kept the label make-up of
# fixed 400-episode sets both in seen scenes (pairs 400-599) and on val_object's glassware (scripts/check_physics.py;
# 30 or 40 iterations, Bullet's pyramid friction and IK at 30 Hz each cut the nominal success); opt-in: seen scenes
# lose nominal grasps under it (7 lost / 0 won on pairs 400-599, 8 / 0 and Fisher p 0.036 on pairs 600-799, which
# fails the rule there) and the sealed catalogue is not checked. `prefix`: `reference` physics with prefix reuse,
# the nominal runs byte for byte, the injected runs' label make-up kept on seen pairs 600-799 and on pairs 400-599 of
# val_object, val_scene and val_both (98-99 % of injected labels the same), physics alone about 1.3x; opt-in (the
# sealed catalogue is not checked; docs/EXPERIMENTS.md, 6 Dec).
PHYSICS = {
    "reference": Physics(),
    "fast": Physics(torsional_friction=False),
    "prefix": Physics(reuse_prefix=True),
}
DEFAULT_PHYSICS = "reference"


def physics_preset(name: Any) -> Physics:
    """The settings of a preset name; a ValueError naming the choices otherwise."""
    if not isinstance(name, str) or name not in PHYSICS:
        raise ValueError(f"physics: unknown preset {name!r}; expected one of {', '.join(PHYSICS)}")
    return PHYSICS[name]


def _no_torsional_friction(cid: int) -> None:
    for i in range(p.getNumBodies(physicsClientId=cid)):
        body = p.getBodyUniqueId(i, physicsClientId=cid)
        for link in range(-1, p.getNumJoints(body, physicsClientId=cid)):
            p.changeDynamics(body, link, spinningFriction=0.0, rollingFriction=0.0, physicsClientId=cid)


def _yaml_mapping(key: str, path: str | None) -> dict[str, Any] | None:
    """A YAML file holding a mapping, or None when no file is named."""
    if path is None:
        return None
    if isinstance(path, dict):  # already loaded (kwargs handed on to a worker)
        return path
    pth = Path(path)
    shipped = CONFIG_DIR / Path(*pth.parts[1:]) if pth.parts[:1] == ("configs",) else None
    if not pth.is_file() and shipped is not None and shipped.is_file():
        pth = shipped  # a file shipped with the package (configs/scenes/...), asked for from another directory
    if not pth.is_file():
        raise ValueError(f"{key}: no such file {path!r}")
    try:
        data = OmegaConf.to_container(OmegaConf.load(pth), resolve=True)
    except Exception as e:
        raise ValueError(f"{key}: {path} is not valid YAML ({str(e).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{key}: {path} must hold a mapping")
    return data


def _flag(name: str, value: Any) -> bool:
    if not isinstance(value, bool):
        raise ValueError(f"{name}: expected true or false, got {value!r}")
    return value


@register_backend(
    "pybullet",
    image_size=224,
    cameras=["front", "side"],
    wrist=False,
    egl=False,
    camera_jitter=True,
    max_distractors=scene_mod.MAX_DISTRACTORS,
    lowpoly_robot=True,
    scene_family=None,
    object_colours=None,
    button_lamp=False,
    broken_glass=False,
    layered_render=True,
    physics=DEFAULT_PHYSICS,
)
class PyBulletSource(ScenarioConfig, Rewinder, FailureSource):
    name = "pybullet"
    TASKS_FILE = TASKS_FILE
    CAMERAS = CAMERAS

    def __init__(
        self,
        image_size: int = 224,
        cameras: Sequence[str] = ("front", "side"),
        wrist: bool = False,
        egl: bool = False,
        render: bool = True,
        tasks_file: str | Path | None = None,
        custom_objects: dict[str, dict[str, Any]] | None = None,
        custom_scene: dict[str, Any] | None = None,
        camera_jitter: bool = True,
        max_distractors: int = scene_mod.MAX_DISTRACTORS,
        lowpoly_robot: bool = True,
        scene_family: str | None = None,
        object_colours: str | None = None,
        button_lamp: bool = False,
        broken_glass: bool = False,
        layered_render: bool = True,
        physics: str = DEFAULT_PHYSICS,
    ):
        super().__init__()
        self.physics = physics_preset(physics)
        self.reuse_prefix = self.physics.reuse_prefix
        self.camera_jitter, self.max_distractors, self.lowpoly_robot = (
            camera_jitter,
            int(max_distractors),
            lowpoly_robot,
        )
        self.scene_family = scene_family  # None: the variant's own family (scene.SCENE_FAMILIES)
        self.object_colours = object_colours  # None: the catalogue's colours (scene.OBJECT_COLOURS)
        # A button's cap travels 12 mm and springs back, which a keyframe of a few hundred pixels does not show: with
        # the lamp on, the housing of a button the task must press renders lit in every keyframe rendered once its
        # pressed goal holds on the trace so far, so a grid shows a press that happened and a press beside the
        # button. Off by default: the page's data were rendered without it.
        self.button_lamp = _flag("button_lamp", button_lamp)
        # Glassware that hit something at >= BREAK_SPEED (the labeler's breakage: the Fatal severity) renders as
        # shards from the first keyframe rendered after it comes to rest, instead of standing whole where it fell, so
        # a grid shows the breakage its label claims. Drawn only (no collision, no mass): the trace and labels are
        # the same. Off by default: the page's data were rendered without it.
        self.broken_glass = _flag("broken_glass", broken_glass)
        self._broken: set[str] = set()
        self._lit: dict[int, list[tuple[int, tuple[float, ...]]]] = {}  # lamp body -> its shapes' unlit colours
        self._changed = False  # a physics event changed a parameter since the scene was built
        self.cfg = self.load_task_config(tasks_file)
        self.cid = p.connect(p.DIRECT)
        if egl:
            import pkgutil

            egl_mod = pkgutil.get_loader("eglRenderer")
            if egl_mod is None:
                raise ValueError("egl: the eglRenderer plugin is not available in this PyBullet build")
            p.loadPlugin(egl_mod.get_filename(), "_eglRendererPlugin", physicsClientId=self.cid)
        # Layered rendering (render.Renderer) gives the same images pixel for pixel; off renders the whole scene
        # at every keyframe, for a side-by-side benchmark (scripts/bench_sim.py).
        layered = _flag("layered_render", layered_render)
        if render:  # the views' names, as every backend checks them (FailureSource.check_cameras)
            self.check_cameras(cameras)
        self.renderer = Renderer(self.cid, cameras, image_size, wrist, egl, layered) if render else None
        self.custom_objects = custom_objects
        self.custom_scene = custom_scene
        self.scene: scene_mod.Scene | None = None
        self.plan: Plan | None = None
        self._trace: Trace | None = None
        self._steps = 0

    # -- configuration (no simulator needed) ----------------------------------------------------------
    @classmethod
    def prepare_kwargs(cls, kwargs: dict[str, Any]) -> dict[str, Any]:
        """Load and check the `custom_objects` / `custom_scene` YAML files named in `backend_kwargs`."""
        out = dict(kwargs)
        objs = out["custom_objects"] = _yaml_mapping("custom_objects", kwargs.get("custom_objects"))
        for name, spec in (objs or {}).items():
            if not isinstance(spec, dict) or spec.get("kind") not in MOVABLE:
                raise ValueError(f"custom_objects: object {name!r} needs kind: vessel or rod")
            need = ("radius", "height", "rgba") if spec["kind"] == "vessel" else ("radius", "length", "rgba")
            for k in need:
                if k not in spec:
                    raise ValueError(f"custom_objects: object {name!r} is missing {k!r}")
            # The Panda's fingers open to 8 cm: a wider vessel cannot be grasped at all.
            if spec["kind"] == "vessel" and not 0.01 <= float(spec["radius"]) <= 0.038:
                raise ValueError(
                    f"custom_objects: object {name!r} radius must be 0.01-0.038 m (the gripper opens 8 cm)"
                )
        if not is_int(out.get("max_distractors", 0), 0):
            raise ValueError(f"max_distractors: must be a non-negative integer, got {out.get('max_distractors')!r}")
        scene = out["custom_scene"] = _yaml_mapping("custom_scene", kwargs.get("custom_scene"))
        for k in ("bench", "floor", "light"):
            if scene is not None and k not in scene:
                raise ValueError(f"custom_scene: missing {k!r}")
        if scene is not None and "vary" in scene:
            scene_mod.vary_keys(scene["vary"])
        # checked before run.json is written (a resume compares it)
        for flag in ("button_lamp", "broken_glass", "layered_render"):
            _flag(flag, out.get(flag, False))
        physics_preset(out.get("physics", DEFAULT_PHYSICS))
        scene_mod.check_draws(out.get("scene_family"), out.get("object_colours"))  # before any episode
        return out

    # -- FailureSource ------------------------------------------------------------------------------
    def _reset(self, scenario: str, seed: int, variant: str) -> None:
        sc = self._scenario(scenario)
        cid = self.cid
        self._trace = None  # the last episode's: a lamp must not read it for the new scene
        self._broken, self._lit, self._changed = set(), {}, False
        p.resetSimulation(physicsClientId=cid)
        if self.renderer is not None:
            self.renderer.forget_scene()  # a build that fails must not leave the old backdrops on new body ids
        p.setPhysicsEngineParameter(
            deterministicOverlappingPairs=1,
            numSolverIterations=self.physics.solver_iterations,
            fixedTimeStep=DT,
            solverResidualThreshold=SOLVER_RESIDUAL,
            physicsClientId=cid,
        )
        p.setGravity(0, 0, -9.81, physicsClientId=cid)
        rng = np.random.default_rng(seed)
        self.scene = scene_mod.build(
            cid,
            sc["layout"],
            variant,
            rng,
            self.custom_objects,
            self.custom_scene,
            lowpoly=self.lowpoly_robot,
            family=self.scene_family,
        )
        self.plan = Plan(self.scene)  # from the scene's layout (object homes), not from its physics state
        task_templates(self.name)[sc["template"]].cls(self.plan, dict(sc.get("params", {})))
        scene_mod.add_distractors(
            self.scene, sc["layout"], variant, rng, self.max_distractors, [(k.pos, k.quat) for k in self.plan.keyframes]
        )
        scene_mod.recolour_glassware(self.scene, variant, self.object_colours, np.random.default_rng([seed, 0xC0105]))
        if not self.physics.torsional_friction:
            _no_torsional_friction(cid)
        if self.renderer is not None:
            self.renderer.set_episode(self.scene.appearance, rng if self.camera_jitter else None)
            lamps = [o.body for o in self.scene.objects.values() if o.kind == "button"] if self.button_lamp else []
            self.renderer.set_scene(moving_bodies=lamps)
        for _ in range(60):  # let liquid and glassware settle before the first keyframe
            p.stepSimulation(physicsClientId=cid)

    def scripted_keyframes(self) -> list[Keyframe]:
        assert self.plan is not None, "reset() first"
        return list(self.plan.keyframes)

    def object_positions(self) -> dict[str, tuple[float, float, float]]:
        assert self.scene is not None, "reset() first"
        out = {k: tuple(v.home) for k, v in self.scene.objects.items()}
        out.update(self.scene.zones)
        return out

    # -- stepping primitives ---------------------------------------------------------------------------
    def _begin(self) -> None:
        assert self.scene is not None
        self._trace = Trace(self.scene)
        self._steps = 0  # physics steps since begin(): the trace clock
        self._trace.sample(0.0, 0)

    def _physics_step(self, kf_index: int) -> None:
        p.stepSimulation(physicsClientId=self.cid)
        self._steps += 1
        if self._steps % TRACE_EVERY == 0:
            self._trace.sample(self._steps * DT, kf_index)

    def _move(self, kf: Keyframe, index: int) -> None:
        assert self.scene is not None
        robot = self.scene.robot
        robot.set_gripper(kf.gripper)
        robot.move_to(kf.pos, kf.quat, kf.speed, lambda: self._physics_step(index), settle_steps=kf.settle_steps)
        self._trace.sample(self._steps * DT, index)
        self._trace.kf_end.append(len(self._trace.cols["t"]) - 1)

    def _settle(self) -> None:
        # Samples keep the last keyframe's program counter, as the controller still holds it.
        last = max(0, len(self._trace.kf_end) - 1)
        for _ in range(90):
            self._physics_step(last)

    def render(self) -> list[np.ndarray]:
        assert self.scene is not None
        if self.button_lamp and self._trace is not None:
            self._light_pressed_buttons()
        if self.broken_glass and self._trace is not None:
            self._break_glass()
        return self.renderer.render(self.scene.robot.id) if self.renderer is not None else []

    def _light_pressed_buttons(self) -> None:
        """Light the housing of each button goal that holds on the trace so far (the labeler's own predicate, so a
        lit frame and the label agree up to the settling after the last keyframe); it stays lit (the travel is a
        running maximum), and a new episode rebuilds the scene with lamps off."""
        for goal in self.plan.goals:  # the trace holds every button's travel from its first sample (_begin)
            if goal.kind == "button" and GOALS["button"](self._trace.cols, {}, g := goal.to_dict()):
                body = self.scene.objects[g["object"]].body
                if body not in self._lit:  # its unlit colours, for a rewind to before the press (_rewind)
                    shapes = p.getVisualShapeData(body, physicsClientId=self.cid)
                    self._lit[body] = [(k, tuple(v[7])) for k, v in enumerate(x for x in shapes if x[1] == -1)]
                p.changeVisualShape(body, -1, rgbaColor=assets.LAMP_RGBA, physicsClientId=self.cid)

    def _settled_images(self) -> list[np.ndarray] | None:
        # A piece that broke, or came to rest broken, in the settling after the last keyframe (a tube released over
        # its rack that falls after the retreat) is in no keyframe; the labeler calls it Fatal at the last keyframe,
        # so that keyframe is drawn again at the settled state, the one the labels are read on.
        if not self.broken_glass or self.renderer is None or self._trace is None:
            return None
        drawn = len(self._broken)
        self._break_glass(settled=True)
        return self.render() if len(self._broken) > drawn else None  # lamps lit as in every keyframe

    def _break_glass(self, settled: bool = False) -> None:
        """Draw each task object whose trace so far holds a breaking impact (the labeler's `impact_speed`) as shards
        where it lies, once it has come to rest (its base slower than LANDED m/s, read from the simulator, which
        changes nothing; `settled`: the episode's end, where lying on something will do, as a piece still rolling
        on the bench lies there: a contact from below, not the hand's), and hide the whole object. It stays broken;
        a new episode rebuilds the scene. Drawn from the physics as the labeler reads it (`labeler.broken`): a grid
        shows shards where its label's Fatal severity is a breakage, but for a piece in the air at the end."""
        cols, cid = self._trace.cols, self.cid
        for name, obj in self._trace.movables.items():
            if name in self._broken or f"{name}.pos" not in cols:
                continue
            moving = math.hypot(*p.getBaseVelocity(obj.body, physicsClientId=cid)[0]) > LANDED
            if moving and not settled:
                continue
            if impact_speed({f"{name}.pos": cols[f"{name}.pos"], "rate_hz": TRACE_RATE_HZ}, name) < BREAK_SPEED:
                continue
            # the surface it lies on: the AABB of a tipped compound is loose (up to 12 mm under a vessel on its side)
            contacts = p.getContactPoints(bodyA=obj.body, physicsClientId=cid)
            touch = [c[5][2] for c in contacts]
            robot = self.scene.robot.id
            if moving and not any(c[2] != robot and c[7][2] > 0.7 for c in contacts):  # normal on B: up from below
                continue
            lo, hi = p.getAABB(obj.body, physicsClientId=cid)
            centre = ((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, min(touch) if touch else lo[2])
            rgba = p.getVisualShapeData(obj.body, physicsClientId=cid)[0][7]
            p.changeVisualShape(obj.body, -1, rgbaColor=(*rgba[:3], 0.0), physicsClientId=cid)
            assets.shards(cid, centre, obj.dims["radius"], rgba, stub=obj.kind == "vessel")
            self._broken.add(name)

    def camera_matrices(self) -> list[list[float]] | None:
        assert self.scene is not None
        return self.renderer.matrices(self.scene.robot.id) if self.renderer is not None else None

    @property
    def camera_names(self) -> list[str]:
        return list(self.renderer.views) if self.renderer is not None else []

    def trace_so_far(self) -> dict[str, Any]:
        return self._trace.to_dict()

    def close(self) -> None:
        if self.cid is not None and p.isConnected(self.cid):
            p.disconnect(self.cid)
        self.cid = None  # type: ignore[assignment]

    # -- helpers -------------------------------------------------------------------------------------
    def _apply_physics(self, ev: PhysicsEvent) -> None:
        scene, cid = self.scene, self.cid
        assert scene is not None
        self._changed = True
        if ev.param == "grip_force":
            scene.robot.grip_force *= ev.scale
            scene.robot.set_gripper(scene.robot.gripper_cmd)
            return
        if ev.param.startswith("liquid_"):
            for b in scene.particles.get(ev.target, []):
                info = p.getDynamicsInfo(b, -1, physicsClientId=cid)
                if ev.param == "liquid_mass":
                    p.changeDynamics(b, -1, mass=info[0] * ev.scale, physicsClientId=cid)
                elif ev.param == "liquid_friction":
                    p.changeDynamics(b, -1, lateralFriction=info[1] * ev.scale, physicsClientId=cid)
                else:  # liquid_viscosity: the particles' viscous drag stands in for the liquid's viscosity
                    p.changeDynamics(b, -1, linearDamping=assets.LIQUID_DAMPING * ev.scale, physicsClientId=cid)
            return
        body = scene.body(ev.target)
        info = p.getDynamicsInfo(body, -1, physicsClientId=cid)
        if ev.param == "friction":
            p.changeDynamics(body, -1, lateralFriction=info[1] * ev.scale, physicsClientId=cid)
        elif ev.param == "mass":
            p.changeDynamics(body, -1, mass=info[0] * ev.scale, physicsClientId=cid)

    def task_meta(self, executed: Sequence[Keyframe]) -> TaskMeta:
        scene, plan = self.scene, self.plan
        assert scene is not None and plan is not None
        return TaskMeta(
            steps=plan.steps,
            goals=plan.goals,
            objects={k: ObjectInfo(o.kind, o.dims, list(o.home)) for k, o in scene.objects.items()},
            places={k: list(v) for k, v in self.object_positions().items()},
            nominal=[NominalKeyframe(k.name, list(k.pos), list(k.quat), k.gripper, k.segment) for k in plan.keyframes],
            executed=[k.name for k in executed],
            bench_top=assets.BENCH_TOP,
            liquid_total={k: len(v) for k, v in scene.particles.items()},
            labels=scene.labels,
            description=self.describe(self._key[0], self.scene.labels),
            robot_base=list(scene.robot.base),
        )
