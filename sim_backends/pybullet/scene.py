"""Builds one scenario's bench: robot, glassware, rack, oven, button, zones and liquid.

Object kinds come from a catalogue (seen objects) or, for the unseen sets, from
a held-out catalogue or a user's definition file; the scene's appearance
(bench and floor colours, texture, light) likewise. Everything random is drawn
from the episode's seed, so (scenario, seed, variant) fixes the initial state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pybullet as p

from sim_backends.pybullet import assets
from sim_backends.pybullet.robot import Panda

# Seen objects (training distribution). Vessels: radius/height in metres, Panda's fingers open to 8 cm.
SEEN_OBJECTS: dict[str, dict[str, Any]] = {
    "beaker_small": {"kind": "vessel", "radius": 0.025, "height": 0.085, "sides": 8, "rgba": [0.70, 0.88, 0.95, 1]},
    "beaker_large": {"kind": "vessel", "radius": 0.034, "height": 0.10, "sides": 8, "rgba": [0.62, 0.84, 0.92, 1]},
    "flask": {"kind": "vessel", "radius": 0.034, "height": 0.11, "sides": 7, "neck_radius": 0.02,
              "rgba": [0.75, 0.90, 0.85, 1]},
    "bottle": {"kind": "vessel", "radius": 0.026, "height": 0.10, "sides": 6, "rgba": [0.45, 0.30, 0.15, 1]},
    "glass_rod": {"kind": "rod", "length": 0.22, "radius": 0.006, "rgba": [0.85, 0.95, 1.0, 1]},
    "test_tube": {"kind": "rod", "length": 0.12, "radius": 0.009, "rgba": [0.80, 0.93, 0.98, 1]},
}

# Held-out objects for the unseen-object set: shapes, colours and sizes absent from the seen catalogue.
UNSEEN_OBJECTS: dict[str, dict[str, Any]] = {
    "beaker_small": {"kind": "vessel", "radius": 0.025, "height": 0.075, "sides": 6, "rgba": [0.95, 0.75, 0.35, 1]},
    "beaker_large": {"kind": "vessel", "radius": 0.037, "height": 0.09, "sides": 10, "rgba": [0.90, 0.55, 0.70, 1]},
    "flask": {"kind": "vessel", "radius": 0.036, "height": 0.10, "sides": 6, "neck_radius": 0.024,
              "rgba": [0.95, 0.85, 0.40, 1]},
    "bottle": {"kind": "vessel", "radius": 0.024, "height": 0.09, "sides": 10, "rgba": [0.30, 0.50, 0.20, 1]},
    "glass_rod": {"kind": "rod", "length": 0.20, "radius": 0.007, "rgba": [0.95, 0.60, 0.30, 1]},
    "test_tube": {"kind": "rod", "length": 0.11, "radius": 0.010, "rgba": [0.85, 0.55, 0.95, 1]},
}

SEEN_SCENES: list[dict[str, Any]] = [
    {"bench": [0.82, 0.80, 0.76, 1], "floor": [0.35, 0.35, 0.38, 1], "light": [0.6, -0.4, 2.0], "checker": False},
    {"bench": [0.78, 0.78, 0.80, 1], "floor": [0.30, 0.33, 0.30, 1], "light": [0.2, 0.6, 2.0], "checker": False},
    {"bench": [0.86, 0.83, 0.72, 1], "floor": [0.40, 0.36, 0.33, 1], "light": [-0.3, -0.5, 2.0], "checker": False},
]
UNSEEN_SCENES: list[dict[str, Any]] = [
    {"bench": [0.25, 0.28, 0.32, 1], "floor": [0.70, 0.62, 0.48, 1], "light": [1.5, 1.0, 1.0], "checker": True},
    {"bench": [0.55, 0.40, 0.28, 1], "floor": [0.15, 0.20, 0.35, 1], "light": [-1.0, 1.2, 1.2], "checker": True},
]

@dataclass
class SceneObject:
    name: str  # role name in the task: "obj", "src", "dest_vessel", ...
    kind: str  # vessel | rod | oven | button | rack
    body: int
    home: tuple[float, float, float]
    dims: dict[str, float] = field(default_factory=dict)


@dataclass
class Scene:
    cid: int
    robot: Panda
    objects: dict[str, SceneObject]
    zones: dict[str, tuple[float, float, float]]
    particles: dict[str, list[int]]  # vessel name -> particle ids initially inside it
    appearance: dict[str, Any]
    bench_id: int = -1
    labels: dict[str, str] = field(default_factory=dict)  # role -> words used in task text and corrections

    def body(self, name: str) -> int:
        return self.objects[name].body


def _checker_texture(cid: int, rgba: list[float], seed: int) -> int:
    """A procedural checker texture written to a temp PNG (PyBullet loads textures from files only)."""
    import os
    import tempfile

    from PIL import Image

    rng = np.random.default_rng(seed)
    base = np.array(rgba[:3]) * 255
    alt = np.clip(base * (0.6 + 0.3 * rng.random()), 0, 255)
    tile = np.kron((np.indices((8, 8)).sum(0) % 2)[..., None], np.ones((16, 16, 1)))
    img = (tile * base + (1 - tile) * alt).astype(np.uint8)
    fd, path = tempfile.mkstemp(suffix=".png")
    os.close(fd)
    Image.fromarray(img).save(path)
    try:
        return p.loadTexture(path, physicsClientId=cid)
    finally:
        os.unlink(path)


# Words for the objects in task descriptions and correction instructions (custom objects may set `label`).
OBJECT_LABELS = {"beaker_small": "small beaker", "beaker_large": "large beaker", "flask": "Erlenmeyer flask",
                 "bottle": "reagent bottle", "glass_rod": "glass rod", "test_tube": "test tube"}
KIND_LABELS = {"oven": "drying oven", "button": "button", "rack": "test tube rack", "zone": "target area"}


def resolve_object(kind_name: str, variant: str, custom: dict[str, dict[str, Any]] | None) -> dict[str, Any]:
    if custom and kind_name in custom:
        return custom[kind_name]
    table = UNSEEN_OBJECTS if variant in ("unseen_object", "unseen_both") else SEEN_OBJECTS
    if kind_name not in table:
        raise ValueError(f"scenario: unknown object {kind_name!r}; known: {', '.join(sorted(table))}")
    return table[kind_name]


def build(cid: int, layout: dict[str, Any], variant: str, rng: np.random.Generator,
          custom_objects: dict[str, dict[str, Any]] | None = None,
          custom_scene: dict[str, Any] | None = None, grip_force: float = 60.0) -> Scene:
    """Create the scene described by a scenario's `layout` (role -> {object, xy, ...})."""
    if custom_scene is not None:
        appearance = custom_scene
    else:
        pool = UNSEEN_SCENES if variant in ("unseen_scene", "unseen_both") else SEEN_SCENES
        appearance = dict(pool[int(rng.integers(len(pool)))])
    bench_id, floor_id = assets.bench(cid, rgba=appearance["bench"], floor_rgba=appearance["floor"])
    if appearance.get("checker"):
        tex = _checker_texture(cid, appearance["bench"], int(rng.integers(1 << 30)))
        p.changeVisualShape(bench_id, -1, textureUniqueId=tex, physicsClientId=cid)
    robot = Panda(cid, grip_force=grip_force)
    objects: dict[str, SceneObject] = {}
    zones: dict[str, tuple[float, float, float]] = {}
    parts: dict[str, list[int]] = {}
    labels: dict[str, str] = {}
    jitter = float(layout.get("_jitter", 0.015))
    for role, spec in layout.items():
        if role.startswith("_"):
            continue
        if "object" in spec:
            od0 = resolve_object(spec["object"], variant, custom_objects)
            labels[role] = str(spec.get("label") or od0.get("label") or OBJECT_LABELS.get(spec["object"])
                               or spec["object"].replace("_", " "))
        else:
            labels[role] = str(spec.get("label") or KIND_LABELS.get(spec.get("kind", ""), role.replace("_", " ")))
        xy = np.asarray(spec["xy"], float) + rng.uniform(-jitter, jitter, 2) * float(spec.get("jitter", 1.0))
        kind = spec.get("kind") or resolve_object(spec["object"], variant, custom_objects)["kind"]
        if kind == "zone":
            pos = (float(xy[0]), float(xy[1]), assets.BENCH_TOP)
            assets.zone(cid, pos, radius=spec.get("radius", 0.05), rgba=spec.get("rgba", (0.2, 0.8, 0.3, 1)))
            zones[role] = pos
            continue
        if kind == "oven":
            pos = (float(xy[0]), float(xy[1]), assets.BENCH_TOP)
            body, _ = assets.oven(cid, pos, open_angle=float(spec.get("open_angle", 0.0)))
            objects[role] = SceneObject(role, "oven", body, pos, {"width": 0.24, "depth": 0.22, "height": 0.18})
            continue
        if kind == "button":
            pos = (float(xy[0]), float(xy[1]), assets.BENCH_TOP)
            body, _ = assets.button(cid, pos, rgba=spec.get("rgba", (0.85, 0.1, 0.1, 1)))
            objects[role] = SceneObject(role, "button", body, pos, {"travel": 0.012, "top": 0.05})
            continue
        if kind == "rack":
            pos = (float(xy[0]), float(xy[1]), assets.BENCH_TOP)
            body = assets.rack(cid, pos)
            objects[role] = SceneObject(role, "rack", body, pos, {"height": assets.RACK_HEIGHT})
            for i, h in enumerate(assets.hole_positions(pos)):
                zones[f"{role}_hole{i}"] = (h[0], h[1], assets.BENCH_TOP)
                labels[f"{role}_hole{i}"] = f"hole {i + 1} of the {labels[role]}"
            continue
        od = resolve_object(spec["object"], variant, custom_objects)
        z0 = float(spec.get("z", 0.0)) + assets.BENCH_TOP
        if od["kind"] == "vessel":
            vs = assets.VesselSpec(radius=od["radius"], height=od["height"], sides=int(od.get("sides", 8)),
                                   neck_radius=float(od.get("neck_radius", 0.0)), rgba=tuple(od["rgba"]),
                                   mass=float(od.get("mass", 0.12)))
            pos = (float(xy[0]), float(xy[1]), z0)
            body = assets.vessel(cid, vs, pos)
            objects[role] = SceneObject(role, "vessel", body, pos,
                                        {"radius": vs.radius, "height": vs.height, "neck": vs.neck_radius})
            n = int(spec.get("liquid", 0))
            if n:
                parts[role] = assets.particles(cid, (pos[0], pos[1], z0 + 0.006), n)
        elif od["kind"] == "rod":
            ln = float(od["length"])
            if "in" in spec:  # standing in a rack hole
                hx, hy, _ = zones[spec["in"]]
                pos = (hx, hy, z0 + 0.006 + ln / 2)
            else:
                pos = (float(xy[0]), float(xy[1]), z0 + ln / 2)
            body = assets.rod(cid, pos, length=ln, radius=float(od["radius"]), rgba=tuple(od["rgba"]))
            objects[role] = SceneObject(role, "rod", body, pos, {"length": ln, "radius": float(od["radius"])})
        else:
            raise ValueError(f"scenario: object {spec['object']!r} has unknown kind {od['kind']!r}")
    return Scene(cid, robot, objects, zones, parts, appearance, bench_id, labels)
