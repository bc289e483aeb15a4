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


class Renderer:
    def __init__(self, cid: int, views: Sequence[str], size: int, wrist: bool = False, egl: bool = False):
        unknown = [v for v in views if v not in CAMERAS]
        if unknown:
            raise ValueError(f"cameras: unknown view(s) {unknown}; available: {', '.join(CAMERAS)}")
        self.cid, self.size = cid, int(size)
        self.views = list(views) + ([WRIST] if wrist else [])
        self.proj = p.computeProjectionMatrixFOV(50.0, 1.0, 0.02, 4.0)
        self.view_mats = {v: p.computeViewMatrix(CAMERAS[v][0], CAMERAS[v][1], (0, 0, 1)) for v in views}
        self.projs = {v: self.proj for v in views}
        self.renderer = p.ER_BULLET_HARDWARE_OPENGL if egl else p.ER_TINY_RENDERER
        self.light = (0.6, -0.4, 2.0)
        self.light_kw: dict[str, float] = {}

    def set_episode(self, appearance: dict, rng: np.random.Generator | None) -> None:
        """Light of the scene's appearance; camera poses jittered from the episode's RNG (None: nominal poses)."""
        self.light = tuple(appearance["light"])
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

    def render(self, robot_id: int) -> list[np.ndarray]:
        out = []
        for v in self.views:
            vm = self._wrist_view(robot_id) if v == WRIST else self.view_mats[v]
            _, _, rgb, _, _ = p.getCameraImage(
                self.size,
                self.size,
                vm,
                self.projs.get(v, self.proj),
                renderer=self.renderer,
                lightDirection=self.light,
                shadow=0,
                **self.light_kw,
                flags=p.ER_NO_SEGMENTATION_MASK,
                physicsClientId=self.cid,
            )
            out.append(np.asarray(rgb, np.uint8).reshape(self.size, self.size, 4)[:, :, :3])
        return out
