"""Builds one scenario's bench: robot, glassware, rack, oven, button, zones and liquid.

Object kinds come from a catalogue (seen objects) or, for the held-out sets, from
the validation or the sealed catalogue, or from a user's definition file; the scene's appearance
(bench and floor colours, texture, light) likewise. Everything random is drawn
from the episode's seed, so (scenario, seed, variant) fixes the initial state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pybullet as p

from labrobfail_vlm.taxonomy import object_set, scene_set
from sim_backends.pybullet import assets
from sim_backends.pybullet.robot import Panda
from sim_backends.schema import MOVABLE

# Seen objects (training distribution). Vessels: radius/height in metres, Panda's fingers open to 8 cm.
SEEN_OBJECTS: dict[str, dict[str, Any]] = {
    "beaker_small": {"kind": "vessel", "radius": 0.025, "height": 0.085, "sides": 8, "rgba": [0.70, 0.88, 0.95, 1]},
    "beaker_large": {"kind": "vessel", "radius": 0.034, "height": 0.10, "sides": 8, "rgba": [0.62, 0.84, 0.92, 1]},
    "flask": {
        "kind": "vessel",
        "radius": 0.034,
        "height": 0.11,
        "sides": 7,
        "neck_radius": 0.02,
        "rgba": [0.75, 0.90, 0.85, 1],
    },
    "bottle": {"kind": "vessel", "radius": 0.026, "height": 0.10, "sides": 6, "rgba": [0.45, 0.30, 0.15, 1]},
    "glass_rod": {"kind": "rod", "length": 0.22, "radius": 0.006, "rgba": [0.85, 0.95, 1.0, 1]},
    "test_tube": {"kind": "rod", "length": 0.12, "radius": 0.009, "rgba": [0.80, 0.93, 0.98, 1]},
}

# Held-out objects of the validation sets (val_object, val_both): shapes, colours and sizes absent from the seen
# catalogue. The tower's any-hue augmentation and its randomised stage were chosen on them: they are no test.
VAL_OBJECTS: dict[str, dict[str, Any]] = {
    "beaker_small": {"kind": "vessel", "radius": 0.025, "height": 0.075, "sides": 6, "rgba": [0.95, 0.75, 0.35, 1]},
    "beaker_large": {"kind": "vessel", "radius": 0.037, "height": 0.09, "sides": 10, "rgba": [0.90, 0.55, 0.70, 1]},
    "flask": {
        "kind": "vessel",
        "radius": 0.036,
        "height": 0.10,
        "sides": 6,
        "neck_radius": 0.024,
        "rgba": [0.95, 0.85, 0.40, 1],
    },
    "bottle": {"kind": "vessel", "radius": 0.024, "height": 0.09, "sides": 10, "rgba": [0.30, 0.50, 0.20, 1]},
    "glass_rod": {"kind": "rod", "length": 0.20, "radius": 0.007, "rgba": [0.95, 0.60, 0.30, 1]},
    "test_tube": {"kind": "rod", "length": 0.11, "radius": 0.010, "rgba": [0.85, 0.55, 0.95, 1]},
}

# The sealed objects (test_object, test_both): cross-sections (sides), sizes and saturated colours that neither
# the seen nor the validation catalogue has. Whole-image colour augmentation (any hue, brightness scaled) can bring a
# trained colour near some of these, so what no training draw makes is the shape and size.
SEALED_OBJECTS: dict[str, dict[str, Any]] = {
    # radius 0.027: at 0.022 (and 0.024 with 11 sides) 7-8 of 18 nominal pours from it slipped or missed the target
    "beaker_small": {"kind": "vessel", "radius": 0.027, "height": 0.08, "sides": 5, "rgba": [0.80, 0.12, 0.14, 1]},
    "beaker_large": {"kind": "vessel", "radius": 0.031, "height": 0.095, "sides": 12, "rgba": [0.12, 0.22, 0.78, 1]},
    "flask": {
        "kind": "vessel",
        "radius": 0.032,
        "height": 0.105,
        "sides": 5,  # a flask's compound has 2 x sides + 1 parts; PyBullet takes 16 at most
        "neck_radius": 0.017,
        "rgba": [0.10, 0.62, 0.60, 1],
    },
    "bottle": {"kind": "vessel", "radius": 0.028, "height": 0.095, "sides": 9, "rgba": [0.55, 0.08, 0.45, 1]},
    "glass_rod": {"kind": "rod", "length": 0.18, "radius": 0.008, "rgba": [0.85, 0.85, 0.10, 1]},
    "test_tube": {"kind": "rod", "length": 0.13, "radius": 0.008, "rgba": [0.95, 0.35, 0.05, 1]},
}
OBJECT_CATALOGUES: dict[str, dict[str, dict[str, Any]]] = {
    "seen": SEEN_OBJECTS,
    "val": VAL_OBJECTS,
    "sealed": SEALED_OBJECTS,
}

# Scene appearance families. Seen, val and sealed never overlap: disjoint bench (and floor) colour ranges and
# texture kinds of their own, so a held-out episode never shows a bench the model was trained on. The sealed family
# is also outside the randomised family that the tower pretrains on (tests/test_splits_sealed.py samples them all).
SCENE_FAMILIES: dict[str, dict[str, Any]] = {
    "seen": {
        "bench_value": (0.68, 0.92),
        "bench_sat": (0.0, 0.18),
        "floor_value": (0.22, 0.42),
        "textures": ("plain", "grain", "speckle"),
    },
    "val": {
        "bench_value": (0.22, 0.50),
        "bench_sat": (0.25, 0.60),
        "floor_value": (0.55, 0.80),
        "textures": ("checker", "tiles"),
    },
    # Sealed: benches more saturated than any other family draws (bench_sat above 0.7), floors with colour (every
    # other family's floor is near grey, floor_sat below 0.3), and texture kinds no other family has.
    "sealed": {
        "bench_value": (0.35, 0.80),
        "bench_sat": (0.75, 0.95),
        "floor_value": (0.45, 0.75),
        "floor_sat": (0.45, 0.75),
        "textures": ("dots", "rings"),
    },
    # Domain randomisation (backend_kwargs.scene_family=randomised on seen episodes) for the vision tower's
    # pretraining data and train-only extra VQA episodes (make reproduce-more MORE_FAMILY=randomised); never in a
    # validation or test split: any bench and floor colour, and texture kinds that no split uses, so the
    # tower learns to read the task's objects over backgrounds it must ignore. Its colour range covers the val
    # family's (chosen on val, as the tower's any-hue augmentation on the val glassware); its textures never include
    # the val family's checker or tiles, and neither its colours nor its textures reach the sealed family's as drawn.
    # A contrast or saturation gain in colour augmentation would (any family's dark pixels included): every training
    # setting keeps each pixel's saturation at most what it was (augment.raise_saturation: false, from 6 Dec; the
    # tower shipped before then was trained raising it; tests/test_splits_sealed.py).
    "randomised": {
        "bench_value": (0.15, 0.95),
        "bench_sat": (0.0, 0.7),
        "floor_value": (0.1, 0.9),
        "textures": ("plain", "grain", "speckle", "stripes", "blotches"),
    },
}
FLOOR_SAT = (0.0, 0.3)  # a family's floor saturation unless it names its own
PLACEMENT_JITTER = 0.035  # m: objects and zones move by up to this much in x and y (times their `jitter`)
# Glassware colours drawn per episode (backend_kwargs.object_colours=randomised on seen-catalogue episodes) for the
# vision tower's pretraining data only, as the randomised scene family is for benches: any hue, saturation up to 0.8,
# so the tower sees glassware as saturated as the validation catalogue's (0.39-0.68; the seen catalogue's is mostly
# 0.15-0.33) and never as saturated as the sealed catalogue's (0.84-0.95). Colour augmentation cannot do this without
# bringing benches and floors into the sealed scene family's saturation (docs/EXPERIMENTS.md, 6 Dec night).
OBJECT_COLOURS: dict[str, dict[str, tuple[float, float]]] = {
    "randomised": {"value": (0.35, 0.95), "sat": (0.05, 0.80)},
}
MAX_DISTRACTORS = 3  # glassware on the bench that is not part of the task
DISTRACTOR_CLEARANCE = 0.11  # m from every task object and zone (and 0.08 from the lines between them)
SWEEP_CLEARANCE = 0.13  # m (xy) from every link origin of the arm's sweep (links are up to ~0.1 m wide) ...
SWEEP_HEIGHT = 0.30  # m: ... that passes lower than this (the tallest glassware plus the link's reach)
ARM_CORRIDOR = 0.24  # m behind (-x of) each object and zone that the hand and forearm sweep when reaching it


def _rgb(rng: np.random.Generator, value: tuple[float, float], sat: tuple[float, float]) -> list[float]:
    """A colour of random hue with its HSV value and saturation drawn from the given ranges."""
    import colorsys

    r, g, b = colorsys.hsv_to_rgb(float(rng.random()), float(rng.uniform(*sat)), float(rng.uniform(*value)))
    return [round(r, 3), round(g, 3), round(b, 3), 1.0]


def scene_family(variant: str, override: str | None = None) -> str:
    """The appearance family of an episode. `override` replaces the seen family only: a held-out-scene episode keeps
    its own family, so one generation setting serves a tower run's seen and held-out shards alike."""
    if override is not None and override not in SCENE_FAMILIES:
        raise ValueError(f"scene_family: unknown family {override!r}; expected one of {', '.join(SCENE_FAMILIES)}")
    if override in ("val", "sealed"):  # seen-variant episodes on held-out benches would carry them into training
        raise ValueError(
            f"scene_family: {override} is the {override} splits' own family; use variant=val_scene or test_scene"
        )
    held = scene_set(variant)
    return held if held != "seen" else override or "seen"


def check_draws(family: str | None, colours: str | None) -> None:
    """backend_kwargs' scene_family and object_colours: an unknown name is refused in one line."""
    if family is not None:
        scene_family("seen", family)
    if colours is not None and colours not in OBJECT_COLOURS:
        raise ValueError(f"object_colours: expected null or one of {', '.join(OBJECT_COLOURS)}, got {colours!r}")


def draw_appearance(variant: str, rng: np.random.Generator, family: str | None = None) -> dict[str, Any]:
    """Bench and floor colours, bench texture and light of one episode (seeded); `family`: see scene_family."""
    fam = SCENE_FAMILIES[scene_family(variant, family)]
    az, el = rng.uniform(0, 2 * math.pi), rng.uniform(math.radians(35), math.radians(80))
    return {
        "bench": _rgb(rng, fam["bench_value"], fam["bench_sat"]),
        "floor": _rgb(rng, fam["floor_value"], fam.get("floor_sat", FLOOR_SAT)),
        "texture": str(fam["textures"][int(rng.integers(len(fam["textures"])))]),
        "light": [
            round(2 * math.cos(el) * math.cos(az), 3),
            round(2 * math.cos(el) * math.sin(az), 3),
            round(2 * math.sin(el), 3),
        ],
        "ambient": round(float(rng.uniform(0.5, 0.7)), 3),
        "diffuse": round(float(rng.uniform(0.3, 0.5)), 3),
    }


# `vary` names in a custom scene -> the appearance keys drawn for them (draw_appearance)
VARY = {"bench": ("bench",), "floor": ("floor",), "texture": ("texture",), "light": ("light", "ambient", "diffuse")}


def vary_keys(names: list[str]) -> list[str]:
    """A scene file's `vary` list checked and expanded to appearance keys."""
    if not isinstance(names, list):
        raise ValueError(f"custom_scene: vary must be a list of factors, got {names!r}")
    bad = [n for n in names if n not in VARY]
    if bad:
        raise ValueError(f"custom_scene: vary: unknown factor {bad[0]!r}; expected some of {', '.join(VARY)}")
    return [k for n in names for k in VARY[n]]


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
    distractors: dict[str, int] = field(default_factory=dict)  # glassware that is not part of the task -> body

    def body(self, name: str) -> int:
        return self.objects[name].body


def _texture(cid: int, kind: str, rgba: list[float], seed: int) -> int | None:
    """A procedural bench texture written to a temp PNG (PyBullet loads textures from files only)."""
    import os
    import tempfile

    from PIL import Image

    if kind == "plain":
        return None
    rng = np.random.default_rng(seed)
    base = np.array(rgba[:3]) * 255
    alt = np.clip(base * (0.6 + 0.3 * rng.random()), 0, 255)
    yy, xx = np.indices((128, 128))
    if kind == "checker":
        mask = ((yy // 16 + xx // 16) % 2).astype(float)
    elif kind == "tiles":  # square tiles with dark grout lines
        mask = ((yy % 32 < 29) & (xx % 32 < 29)).astype(float)
    elif kind == "grain":  # wood-like stripes of varying width
        phase = np.sin(yy / rng.uniform(3, 8) + 2 * np.sin(xx / rng.uniform(20, 40)))
        mask = 0.55 + 0.45 * phase
    elif kind == "speckle":
        mask = 1.0 - 0.5 * (rng.random((128, 128)) < 0.08)
    elif kind == "stripes":  # straight bands at a random angle and period (the randomised family only)
        angle, period = rng.uniform(0, math.pi), rng.uniform(6, 24)
        mask = (np.sin((xx * math.cos(angle) + yy * math.sin(angle)) * 2 * math.pi / period) > 0).astype(float)
    elif kind == "blotches":  # smooth low-frequency patches (the randomised family only)
        coarse = Image.fromarray((rng.random((8, 8)) * 255).astype(np.uint8)).resize((128, 128), Image.BICUBIC)
        mask = np.asarray(coarse, float) / 255.0
    elif kind == "dots":  # round spots on a square lattice of random pitch (the sealed family only)
        pitch = int(rng.integers(10, 22))
        c = pitch / 2
        mask = 1.0 - (((yy % pitch - c) ** 2 + (xx % pitch - c) ** 2) < (0.3 * pitch) ** 2)
    elif kind == "rings":  # concentric rings about a random centre (the sealed family only)
        cy, cx, period = rng.uniform(0, 128), rng.uniform(0, 128), rng.uniform(8, 18)
        mask = (np.sin(np.hypot(yy - cy, xx - cx) * 2 * math.pi / period) > 0).astype(float)
    else:
        kinds = "plain, grain, speckle, stripes, blotches, checker, tiles, dots or rings"
        raise ValueError(f"custom_scene: unknown texture {kind!r}; expected {kinds}")
    img = (mask[..., None] * base + (1 - mask[..., None]) * alt).astype(np.uint8)
    fd, path = tempfile.mkstemp(suffix=".png")
    os.close(fd)
    Image.fromarray(img).save(path)
    try:
        return p.loadTexture(path, physicsClientId=cid)
    finally:
        os.unlink(path)


def _seg_dist(q: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    t = float(np.clip(np.dot(q - a, ab) / max(float(np.dot(ab, ab)), 1e-9), 0.0, 1.0))
    return float(np.linalg.norm(q - (a + t * ab)))


def place_distractors(
    cid: int,
    objects: dict[str, "SceneObject"],
    zones: dict[str, tuple],
    variant: str,
    rng: np.random.Generator,
    count: int,
    sweep: np.ndarray | None = None,
) -> dict[str, int]:
    """Up to `count` vessels from the variant's catalogue, clear of the task's objects, zones and paths.

    They stand away from every object and zone, from the straight lines between them, from the approach
    corridor behind each object and zone (the arm comes in along +x) and from every point of `sweep` (where
    the arm's links pass along the nominal plan) low enough to hit them, so the nominal plan never touches them.
    Without the sweep, all 11 nominal failures in 432 runs were the forearm, wrist or hand hitting a distractor.
    """
    low = sweep[sweep[:, 2] < SWEEP_HEIGHT, :2] if sweep is not None and len(sweep) else np.zeros((0, 2))
    table = OBJECT_CATALOGUES[object_set(variant)]
    kinds = sorted(k for k, v in table.items() if v["kind"] == "vessel")
    items = [np.asarray(o.home[:2]) for o in objects.values()] + [np.asarray(z[:2]) for z in zones.values()]
    segs = [(a, b) for i, a in enumerate(items) for b in items[i + 1 :]]
    # The hand comes in along +x with the forearm trailing low behind it, at every object it grasps and every
    # zone it places on: keep those corridors clear (a distractor behind a target zone blocked the lowering).
    segs += [(it - [ARM_CORRIDOR, 0], it) for it in items]
    segs += [(np.zeros(2), it) for it in items]  # the arm reaches out from its base
    ovens = [np.asarray(o.home[:2]) for o in objects.values() if o.kind == "oven"]
    out: dict[str, int] = {}
    for i in range(count):
        kind = kinds[int(rng.integers(len(kinds)))]
        for _ in range(40):
            q = np.array([rng.uniform(0.30, 0.78), rng.uniform(-0.40, 0.40)])
            if (
                all(np.linalg.norm(q - it) >= DISTRACTOR_CLEARANCE for it in items)
                and all(_seg_dist(q, a, b) >= 0.08 for a, b in segs)
                and all(np.linalg.norm(q - ov) >= 0.32 for ov in ovens)
                and (not len(low) or float(np.min(np.linalg.norm(low - q, axis=1))) >= SWEEP_CLEARANCE)
                and all(
                    np.linalg.norm(q - np.asarray(p.getBasePositionAndOrientation(b, physicsClientId=cid)[0][:2]))
                    >= 0.09
                    for b in out.values()
                )
            ):
                od = table[kind]
                vs = vessel_spec(od)
                body = assets.vessel(cid, vs, (float(q[0]), float(q[1]), assets.BENCH_TOP))
                # A resting distractor sleeps (no solver work) until something touches it.
                p.changeDynamics(body, -1, activationState=p.ACTIVATION_STATE_ENABLE_SLEEPING, physicsClientId=cid)
                out[f"distractor{i}"] = body
                break
    return out


# Words for the objects in task descriptions and correction instructions (custom objects may set `label`).
OBJECT_LABELS = {
    "beaker_small": "small beaker",
    "beaker_large": "large beaker",
    "flask": "Erlenmeyer flask",
    "bottle": "reagent bottle",
    "glass_rod": "glass rod",
    "test_tube": "test tube",
}
KIND_LABELS = {"oven": "drying oven", "button": "button", "rack": "test tube rack", "zone": "target area"}


def resolve_object(kind_name: str, variant: str, custom: dict[str, dict[str, Any]] | None) -> dict[str, Any]:
    if custom and kind_name in custom:
        return custom[kind_name]
    table = OBJECT_CATALOGUES[object_set(variant)]
    if kind_name not in table:
        raise ValueError(f"scenario: unknown object {kind_name!r}; known: {', '.join(sorted(table))}")
    return table[kind_name]


def _appearance(
    variant: str, rng: np.random.Generator, custom_scene: dict[str, Any] | None, family: str | None
) -> dict[str, Any]:
    """The episode's appearance: drawn from its family, or a user's scene file with its `vary` factors drawn."""
    if custom_scene is not None:  # a user's scene file: fixed colours and light; texture optional
        appearance = {
            "texture": "checker" if custom_scene.get("checker") else "plain",
            "ambient": 0.6,
            "diffuse": 0.35,
            **custom_scene,
        }
        if custom_scene.get("vary"):  # these factors are drawn per episode as in the wide world, the rest stay fixed
            drawn = draw_appearance(variant, rng, family)
            appearance.update({k: drawn[k] for k in vary_keys(custom_scene["vary"])})
    else:
        appearance = draw_appearance(variant, rng, family)
    return appearance


def _role_label(role: str, spec: dict[str, Any], variant: str, custom: dict[str, dict[str, Any]] | None) -> str:
    """The words for a layout role in task text and corrections: the spec's, the object's, or the catalogue's."""
    if "object" in spec:
        od0 = resolve_object(spec["object"], variant, custom)
        return str(
            spec.get("label")
            or od0.get("label")
            or OBJECT_LABELS.get(spec["object"])
            or spec["object"].replace("_", " ")
        )
    return str(spec.get("label") or KIND_LABELS.get(spec.get("kind", ""), role.replace("_", " ")))


@dataclass
class _Parts:
    """What `build` collects while it places a layout's roles."""

    objects: dict[str, SceneObject] = field(default_factory=dict)
    zones: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    parts: dict[str, list[int]] = field(default_factory=dict)
    labels: dict[str, str] = field(default_factory=dict)


def _place_fixture(cid: int, role: str, kind: str, spec: dict[str, Any], xy: np.ndarray, out: _Parts) -> bool:
    """Place a zone, oven, button or rack at `xy`; False if `kind` is none of them (glassware)."""
    pos = (float(xy[0]), float(xy[1]), assets.BENCH_TOP)
    if kind == "zone":
        assets.zone(cid, pos, radius=spec.get("radius", 0.05), rgba=spec.get("rgba", (0.2, 0.8, 0.3, 1)))
        out.zones[role] = pos
    elif kind == "oven":
        body, _ = assets.oven(cid, pos, open_angle=float(spec.get("open_angle", 0.0)))
        out.objects[role] = SceneObject(role, "oven", body, pos, {"width": 0.24, "depth": 0.22, "height": 0.18})
    elif kind == "button":
        body, _ = assets.button(cid, pos, rgba=spec.get("rgba", (0.85, 0.1, 0.1, 1)))
        out.objects[role] = SceneObject(role, "button", body, pos, {"travel": 0.012, "top": 0.05})
    elif kind == "rack":
        body = assets.rack(cid, pos)
        out.objects[role] = SceneObject(role, "rack", body, pos, {"height": assets.RACK_HEIGHT})
        for i, h in enumerate(assets.hole_positions(pos)):
            out.zones[f"{role}_hole{i}"] = (h[0], h[1], assets.BENCH_TOP)
            out.labels[f"{role}_hole{i}"] = f"hole {i + 1} of the {out.labels[role]}"
    else:
        return False
    return True


def vessel_spec(od: dict[str, Any], **extra: Any) -> assets.VesselSpec:
    """A catalogue entry's vessel geometry and colour (`extra`: mass, for a task object)."""
    return assets.VesselSpec(
        radius=od["radius"],
        height=od["height"],
        sides=int(od.get("sides", 8)),
        neck_radius=float(od.get("neck_radius", 0.0)),
        rgba=tuple(od["rgba"]),
        **extra,
    )


def _place_glassware(
    cid: int, role: str, spec: dict[str, Any], od: dict[str, Any], xy: np.ndarray, out: _Parts
) -> None:
    """Place a vessel (with its liquid, if any) or a rod (on the bench or standing in a rack hole)."""
    z0 = float(spec.get("z", 0.0)) + assets.BENCH_TOP
    if od["kind"] == "vessel":
        vs = vessel_spec(od, mass=float(od.get("mass", 0.12)))
        pos = (float(xy[0]), float(xy[1]), z0)
        body = assets.vessel(cid, vs, pos)
        out.objects[role] = SceneObject(
            role, "vessel", body, pos, {"radius": vs.radius, "height": vs.height, "neck": vs.neck_radius}
        )
        n = int(spec.get("liquid", 0))
        if n:
            out.parts[role] = assets.particles(cid, (pos[0], pos[1], z0 + 0.006), n)
    elif od["kind"] == "rod":
        ln = float(od["length"])
        if "in" in spec:  # standing in a rack hole
            hx, hy, _ = out.zones[spec["in"]]
            pos = (hx, hy, z0 + 0.006 + ln / 2)
        else:
            pos = (float(xy[0]), float(xy[1]), z0 + ln / 2)
        body = assets.rod(cid, pos, length=ln, radius=float(od["radius"]), rgba=tuple(od["rgba"]))
        out.objects[role] = SceneObject(role, "rod", body, pos, {"length": ln, "radius": float(od["radius"])})
    else:
        raise ValueError(f"scenario: object {spec['object']!r} has unknown kind {od['kind']!r}")


def build(
    cid: int,
    layout: dict[str, Any],
    variant: str,
    rng: np.random.Generator,
    custom_objects: dict[str, dict[str, Any]] | None = None,
    custom_scene: dict[str, Any] | None = None,
    grip_force: float = 60.0,
    lowpoly: bool = True,
    family: str | None = None,
) -> Scene:
    """Create the scene described by a scenario's `layout` (role -> {object, xy, ...})."""
    appearance = _appearance(variant, rng, custom_scene, family)
    bench_id, floor_id = assets.bench(cid, rgba=appearance["bench"], floor_rgba=appearance["floor"])
    tex = _texture(cid, appearance["texture"], appearance["bench"], int(rng.integers(1 << 30)))
    if tex is not None:
        p.changeVisualShape(bench_id, -1, textureUniqueId=tex, physicsClientId=cid)
    robot = Panda(cid, grip_force=grip_force, lowpoly=lowpoly)
    out = _Parts()
    jitter = float(layout.get("_jitter", PLACEMENT_JITTER))
    for role, spec in layout.items():
        if role.startswith("_"):
            continue
        out.labels[role] = _role_label(role, spec, variant, custom_objects)
        xy = np.asarray(spec["xy"], float) + rng.uniform(-jitter, jitter, 2) * float(spec.get("jitter", 1.0))
        kind = spec.get("kind") or resolve_object(spec["object"], variant, custom_objects)["kind"]
        if _place_fixture(cid, role, kind, spec, xy, out):
            continue
        _place_glassware(cid, role, spec, resolve_object(spec["object"], variant, custom_objects), xy, out)
    robot.carries_liquid = bool(out.parts)  # liquid in play: a closed gripper turns slowly (robot.LIQUID_TURN)
    return Scene(cid, robot, out.objects, out.zones, out.parts, appearance, bench_id, out.labels)


def glassware_bodies(scene: Scene) -> list[int]:
    """The bodies of the task's vessels and rods (schema.MOVABLE) and of the distractors."""
    return [o.body for o in scene.objects.values() if o.kind in MOVABLE] + list(scene.distractors.values())


def recolour_glassware(scene: Scene, variant: str, colours: str | None, rng: np.random.Generator) -> None:
    """Each task vessel, rod and distractor of a seen-catalogue episode in a colour drawn from OBJECT_COLOURS[colours]
    (its own `rng`, so the episode's other draws are the same with or without it); held-out catalogues keep theirs."""
    if colours is None or object_set(variant) != "seen":
        return
    fam = OBJECT_COLOURS[colours]
    for body in glassware_bodies(scene):
        p.changeVisualShape(body, -1, rgbaColor=_rgb(rng, fam["value"], fam["sat"]), physicsClientId=scene.cid)


def add_distractors(
    scene: Scene, layout: dict[str, Any], variant: str, rng: np.random.Generator, max_distractors: int, plan_poses: list
) -> None:
    """0..max_distractors glassware vessels that the nominal plan's arm never comes near (`Panda.sweep`)."""
    n = int(rng.integers(max_distractors + 1)) if layout.get("_distractors", True) else 0
    if n:
        sweep = scene.robot.sweep(plan_poses)
        scene.distractors = place_distractors(scene.cid, scene.objects, scene.zones, variant, rng, n, sweep)
