"""Layered rendering (sim_backends/pybullet/render.py): the backdrop of bodies that cannot move, rendered once per
episode, composited with the moving bodies gives the image the whole scene gives, pixel for pixel."""

import numpy as np
import pybullet as p
import pytest

import sim_backends.pybullet.render as render_mod
from sim_backends import make_backend
from sim_backends.pybullet.render import composite, scene_visuals


def _images(layered: bool, scenario: str, lamp: bool) -> tuple[list[list[bytes]], object, list]:
    src = make_backend(
        "pybullet", image_size=96, wrist=True, button_lamp=lamp, max_distractors=2, layered_render=layered
    )
    try:
        src.reset(scenario, 1)
        # A colour changed after the reset (as a lamp does) must be what every frame shows, the first included.
        jointed = next(o.body for o in src.scene.objects.values() if o.kind in ("button", "oven"))
        p.changeVisualShape(jointed, 0, rgbaColor=(0.1, 0.9, 0.2, 1.0), physicsClientId=src.cid)
        ep = src.execute(src.scripted_keyframes())
        return ep.images, src.renderer, scene_visuals(src.cid)
    finally:
        src.close()


@pytest.mark.parametrize(
    "scenario, lamp, ties",
    [
        ("retrieve_from_oven_beaker_small", False, True),
        ("press_button_red", True, False),
        ("press_button_red", False, False),
    ],
)
def test_layered_images_equal_the_whole_scene(scenario, lamp, ties, monkeypatch):
    """Seed 1's oven door meets the oven's body at pixels whose depths tie (a composite that settles them by
    either layer differs there); a button's lamp lights mid-episode (its housing then stays with the moving
    bodies; lamp off, it is backdrop); the wrist camera moves (whole scene always)."""
    settled = []

    def counted(back, front):
        img = composite(back, front)
        settled.append(img is not None)
        return img

    monkeypatch.setattr(render_mod, "composite", counted)
    whole, _, _ = _images(False, scenario, lamp)
    assert not settled  # the whole-scene setting never composites
    layered, renderer, visuals = _images(True, scenario, lamp)
    assert renderer._static and set(renderer._backdrops) == {"front", "side"}  # fixed cameras, layered
    assert True in settled and (False in settled or not ties)  # most composite; the oven's ties render whole
    assert all(rgba[3] > 0 for *_, rgba in visuals)  # no shape left hidden
    assert [len(v) for v in layered] == [len(v) for v in whole] and len(whole) == 3
    for view_whole, view_layered in zip(whole, layered):
        assert view_whole == view_layered  # PNG bytes: the same pixels


def test_composite_takes_the_nearer_layer_and_refuses_a_tie():
    back = (np.full((2, 3, 3), 10, np.uint8), np.array([[0.5, 0.5, 1.0], [0.5, 1.0, 0.5]], np.float32))
    front = (np.full((2, 3, 3), 200, np.uint8), np.array([[0.4, 0.6, 0.3], [1.0, 1.0, 0.7]], np.float32))
    img = composite(back, front)
    assert img is not None
    # nearer front; farther front; only the front drew; the front drew nothing (x2); farther front
    assert img[:, :, 0].tolist() == [[200, 10, 200], [10, 10, 10]]
    tie = (front[0], np.array([[0.4, 0.5, 0.3], [1.0, 1.0, 0.7]], np.float32))  # (0, 1): both layers drew at 0.5
    assert composite(back, tie) is None
