"""Cameras (front, side) jittered per episode, an optional wrist view; TinyRenderer by default, EGL optional."""

from __future__ import annotations

from typing import Sequence

import numpy as np
import pybullet as p

from sim_backends.pybullet.robot import EE_LINK
from sim_backends.types import WRIST

# eye, target: framed on the workspace (x 0.3-0.8 m, |y| < 0.3 m) so a beaker spans ~15 px in a 224 image.
CAMERAS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float], float]] = {
    "front": ((1.05, 0.30, 0.78), (0.50, 0.0, 0.05), 50.0),
    "side": ((0.52, -0.78, 0.46), (0.52, 0.0, 0.06), 50.0),
}


EYE_JITTER = 0.04  # m, per axis: each episode's cameras stand somewhere around their nominal pose
TARGET_JITTER = 0.02  # m, per axis, for the point they look at
FOV_JITTER = 3.0  # degrees


# One visual shape: body, link (-1: base), its index among the link's shapes, its colour.
Visual = tuple[int, int, int, tuple[float, ...]]


def scene_visuals(cid: int) -> list[Visual]:
    out: list[Visual] = []
    for i in range(p.getNumBodies(physicsClientId=cid)):
        body = p.getBodyUniqueId(i, physicsClientId=cid)
        seen: dict[int, int] = {}
        for v in p.getVisualShapeData(body, physicsClientId=cid):
            k = seen[v[1]] = seen.get(v[1], -1) + 1
            out.append((body, v[1], k, tuple(v[7])))
    return out


def composite(back: tuple[np.ndarray, np.ndarray], front: tuple[np.ndarray, np.ndarray]) -> np.ndarray | None:
    """The image two layers (rgb, depth) make together: per pixel, the nearer layer's colour. None when a pixel
    both layers drew has the same depth in each: the depth TinyRenderer returns is rounded from its z-buffer, so
    an equal depth does not tell which fragment the whole scene would keep (measured: at an oven door's edge, the
    door). A strictly nearer depth does, as the rounding keeps the order."""
    drawn = front[1] < 1.0  # 1.0: the far plane, where a layer drew nothing
    if np.any(drawn & (front[1] == back[1])):
        return None
    return np.where((front[1] < back[1])[:, :, None], front[0], back[0])


class Renderer:
    """The cameras of one simulator client.

    Layered (TinyRenderer's default here): a fixed camera's image is the composite of a backdrop, the bodies that
    cannot move (bench, floor, zones, racks, the oven's body) rendered once per episode, and the bodies that can,
    rendered at each keyframe with the backdrop hidden. TinyRenderer's cost is its pixels' fragments, most of which
    are the bench and floor, so a keyframe costs about a third; the composite is the same image pixel for pixel
    (tests/test_render_layers.py). The wrist camera moves, so it always renders the whole scene.
    """

    def __init__(
        self, cid: int, views: Sequence[str], size: int, wrist: bool = False, egl: bool = False, layered: bool = True
    ):
        self.cid, self.size = cid, int(size)
        self.views = list(views) + ([WRIST] if wrist else [])
        self.proj = p.computeProjectionMatrixFOV(50.0, 1.0, 0.02, 4.0)
        self.view_mats = {v: p.computeViewMatrix(CAMERAS[v][0], CAMERAS[v][1], (0, 0, 1)) for v in views}
        self.projs = {v: self.proj for v in views}
        self.renderer = p.ER_BULLET_HARDWARE_OPENGL if egl else p.ER_TINY_RENDERER
        self.light = (0.6, -0.4, 2.0)
        self.light_kw: dict[str, float] = {}
        self.layered = layered and not egl  # EGL renders on a GPU: no fragment cost to save
        self._static: list[Visual] = []  # the backdrop's visuals (hidden while the moving bodies render)
        self._backdrops: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # fixed view -> (rgb, depth) this episode

    def set_episode(self, appearance: dict, rng: np.random.Generator | None) -> None:
        """Light of the scene's appearance; camera poses jittered from the episode's RNG (None: nominal poses)."""
        self.light = tuple(appearance["light"])
        self.forget_scene()  # new poses and light: whole-scene renders until set_scene renders the backdrops
        self.light_kw = {
            "lightAmbientCoeff": float(appearance.get("ambient", 0.6)),
            "lightDiffuseCoeff": float(appearance.get("diffuse", 0.35)),
        }
        for v in self.view_mats:
            eye, target, fov = CAMERAS[v]
            if rng is not None:
                eye = tuple(np.asarray(eye) + rng.uniform(-EYE_JITTER, EYE_JITTER, 3))
                target = tuple(np.asarray(target) + rng.uniform(-TARGET_JITTER, TARGET_JITTER, 3))
                fov = fov + float(rng.uniform(-FOV_JITTER, FOV_JITTER))
            self.view_mats[v] = p.computeViewMatrix(eye, target, (0, 0, 1))
            self.projs[v] = p.computeProjectionMatrixFOV(fov, 1.0, 0.02, 4.0)

    def _wrist_view(self, robot_id: int):
        s = p.getLinkState(robot_id, EE_LINK, computeForwardKinematics=True, physicsClientId=self.cid)
        pos = np.asarray(s[4])
        m = np.asarray(p.getMatrixFromQuaternion(s[5])).reshape(3, 3)
        eye = pos - 0.10 * m[:, 2] + 0.04 * m[:, 0]
        return p.computeViewMatrix(eye, pos + 0.2 * m[:, 2], -m[:, 0])

    def matrices(self, robot_id: int) -> list[list[float]]:
        """Per view, its view matrix then its projection matrix (OpenGL column-major, 16 + 16 floats): where a
        world point lands in that view's image now (the wrist camera moves with the hand)."""
        return [
            [float(x) for x in (self._wrist_view(robot_id) if v == WRIST else self.view_mats[v])]
            + [float(x) for x in self.projs.get(v, self.proj)]
            for v in self.views
        ]

    def forget_scene(self) -> None:
        """Drop the last episode's backdrops (its body ids mean nothing after a reset): whole-scene renders until
        `set_scene`."""
        self._backdrops, self._static = {}, []

    def set_scene(self, moving_bodies: Sequence[int] = ()) -> None:
        """Render this episode's backdrops: call once a scene is built and `set_episode` has placed the cameras,
        before anything changes a colour (the colours read here are the ones restored after each render; after a
        change, PyBullet reports one colour for every shape of a link). Backdrop: the base of each body of zero
        mass (PyBullet never moves it: bench, floor, zones, rack, the oven's body, the Panda's fixed base), but not
        `moving_bodies`, bodies whose colour may change during the episode (a button's lamp)."""
        self.forget_scene()
        fixed_views = [v for v in self.views if v != WRIST]
        if not self.layered or not fixed_views:
            return
        keep = set(moving_bodies)
        visuals = scene_visuals(self.cid)
        fixed = {b for b, link, _, _ in visuals if link == -1 and b not in keep and self._massless(b)}
        self._static = [v for v in visuals if v[0] in fixed and v[1] == -1]
        moving = [v for v in visuals if not (v[0] in fixed and v[1] == -1)]
        try:
            self._show(moving, False)
            self._backdrops = {v: self._shot(self.view_mats[v], self.projs[v]) for v in fixed_views}
        finally:
            self._show(moving, True)

    def _massless(self, body: int) -> bool:
        return p.getDynamicsInfo(body, -1, physicsClientId=self.cid)[0] == 0.0

    def _show(self, visuals: list[Visual], on: bool) -> None:
        for body, link, k, rgba in visuals:
            colour = rgba if on else (*rgba[:3], 0.0)  # TinyRenderer skips a shape of alpha 0
            p.changeVisualShape(body, link, shapeIndex=k, rgbaColor=colour, physicsClientId=self.cid)

    def _shot(self, view_matrix, proj) -> tuple[np.ndarray, np.ndarray]:
        _, _, rgb, depth, _ = p.getCameraImage(
            self.size,
            self.size,
            view_matrix,
            proj,
            renderer=self.renderer,
            lightDirection=self.light,
            shadow=0,
            **self.light_kw,
            flags=p.ER_NO_SEGMENTATION_MASK,
            physicsClientId=self.cid,
        )
        n = self.size
        return np.asarray(rgb, np.uint8).reshape(n, n, 4)[:, :, :3], np.asarray(depth, np.float32).reshape(n, n)

    def _layered(self) -> dict[str, np.ndarray]:
        """The fixed views that the backdrop and the moving bodies settle; every shape is drawn in its own colour
        again afterwards, also after an error."""
        out: dict[str, np.ndarray] = {}
        try:
            self._show(self._static, False)
            for v, back in self._backdrops.items():
                img = composite(back, self._shot(self.view_mats[v], self.projs[v]))
                if img is not None:  # None: a tie the layers cannot settle; the whole scene renders it
                    out[v] = img
        finally:
            self._show(self._static, True)
        return out

    def render(self, robot_id: int) -> list[np.ndarray]:
        out = self._layered() if self._backdrops else {}
        for v in self.views:
            if v not in out:
                vm = self._wrist_view(robot_id) if v == WRIST else self.view_mats[v]
                out[v] = self._shot(vm, self.projs.get(v, self.proj))[0]
        return [out[v] for v in self.views]
