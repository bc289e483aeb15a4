"""The scene spec of a ManiSkill episode (sim_backends/maniskill/backend.py): its appearance, colours and, for
the lab bench, the layout of its objects, drawn from the episode's seed. Needs no simulator."""

from __future__ import annotations

from typing import Any

import numpy as np

from labrobfail_vlm.taxonomy import object_set, scene_set
from sim_backends.maniskill import assets, envs


def scene_spec(cfg: dict[str, Any], sc: dict[str, Any], variant: str, rng: np.random.Generator) -> dict[str, Any]:
    """Appearance, colours and (for the lab bench) the layout of an episode, drawn from its seed."""
    scenes, objects = scene_set(variant), object_set(variant)
    if "sealed" in (scenes, objects):  # a ValueError here is the one-line refusal the generator prints
        raise ValueError(f"variant: {variant} needs the sealed catalogue, which only the pybullet backend defines")
    pool = cfg["scenes"][scenes]
    spec: dict[str, Any] = {"appearance": dict(pool[int(rng.integers(len(pool)))])}
    if objects == "val" and "val_colors" in sc:  # a stock task's objects recoloured, and named by colour
        spec["colors"] = dict(sc["val_colors"])
        spec["labels"] = dict(sc.get("val_labels", {}))
    if "layout" not in sc:
        return spec
    catalogue = cfg["objects"][objects]
    base = np.asarray(envs.ROBOT_BASE, float)
    layout: dict[str, Any] = {}
    labels: dict[str, str] = {}
    jitter = float(sc["layout"].get("_jitter", 0.015))
    for role, item in sc["layout"].items():
        if role.startswith("_"):
            continue
        xy = np.asarray(item["xy"], float) + rng.uniform(-jitter, jitter, 2) * float(item.get("jitter", 1.0))
        xyz = [float(base[0] + xy[0]), float(base[1] + xy[1]), 0.0]
        kind = item.get("kind")
        if kind is None:  # a catalogue object
            if item["object"] not in catalogue:
                raise ValueError(f"scenario: unknown object {item['object']!r}; known: {', '.join(sorted(catalogue))}")
            od = dict(catalogue[item["object"]])
            kind = od["kind"]
            label = str(item.get("label") or od.get("label") or item["object"].replace("_", " "))
            if kind == "vessel":
                dims = {"radius": od["radius"], "height": od["height"], "neck": od.get("neck_radius", 0.0)}
            else:
                xyz[2] = od["length"] / 2 + (0.006 if "in" in item else 0.0)
                if "in" in item:  # standing in a rack hole, named like its zone: <rack>_hole<i>
                    rack_role, _, i = str(item["in"]).rpartition("_hole")
                    xyz[0], xyz[1] = layout[rack_role]["holes"][int(i)]
                dims = {"length": od["length"], "radius": od["radius"]}
            layout[role] = {**od, "kind": kind, "pos": xyz, "dims": dims, "label": label}
        else:
            label = str(item.get("label") or cfg["kind_labels"].get(kind, role.replace("_", " ")))
            dims = {
                "oven": assets.OVEN_DIMS,
                "button": assets.BUTTON_DIMS,
                "rack": {"height": assets.RACK_HEIGHT},
            }.get(kind, {})
            layout[role] = {**item, "kind": kind, "pos": xyz, "dims": dict(dims), "label": label}
            if kind == "rack":
                layout[role]["holes"] = assets.hole_positions(xyz)
                for i in range(len(layout[role]["holes"])):
                    labels[f"{role}_hole{i}"] = f"hole {i + 1} of the {label}"
        labels[role] = label
    spec["layout"] = layout
    spec["labels"] = labels
    return spec
