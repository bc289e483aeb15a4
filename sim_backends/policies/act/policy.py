"""The ACT policy: camera views + proprio -> a chunk of end-effector targets, blended by temporal ensembling.

Every step queries the model (with ensembling) or every k steps (`temporal_ensemble_coeff: null`); the
action is the target position, its rotation (6-D, orthonormalised) and the gripper (> 0.5: closed). ACT has
no stop signal: an attempt is done when its targets stand still (position, orientation and gripper) for
`idle_stop` steps or after `max_ticks`. A correction starts a new attempt with a fresh `max_ticks` (the loop's
`max_steps` bounds the episode): a correction hands control back to the policy to resume the task, which an ACT
that had spent its ticks could not do (most wide-world pours run all 400 without standing still).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from labrobfail_vlm.config import ConfigError
from sim_backends.policies.act.checkpoint import load_checkpoint
from sim_backends.policies.act.data import from_rot6d
from sim_backends.policies.act.modeling_act import ChunkRunner, TemporalEnsembler
from sim_backends.policies.base import Action, EpisodeContext, Policy, PolicyError, register_policy
from sim_backends.source import Observation
from sim_backends.types import matrix_to_quat, rotation_angle

IDLE_POS, IDLE_ROT = 0.002, 0.01  # m, rad between consecutive targets


def still(a: Action, last: Action | None) -> bool:
    """The target did not move: same position, same orientation, same gripper. A pour tilts in place for a
    quarter of its demonstration (about 23 ticks of 100), so position alone would end every pour mid-tilt."""
    return (
        last is not None
        and float(np.linalg.norm(np.subtract(a.pos, last.pos))) < IDLE_POS
        and rotation_angle(a.quat, last.quat) < IDLE_ROT
        and a.gripper == last.gripper
    )


@register_policy("act")
class ACTPolicy(Policy):
    name = "act"

    def __init__(
        self,
        checkpoint: str | None = None,
        device: str = "cpu",
        max_ticks: int = 400,
        idle_stop: int = 8,
        speed: float = 0.3,
    ):
        import torch

        try:
            self.model, self.cfg = load_checkpoint(checkpoint, device)
        except ValueError as e:
            raise ConfigError(str(e)) from None
        self.torch, self.device = torch, device
        self.max_ticks, self.idle_stop, self.speed = int(max_ticks), int(idle_stop), float(speed)
        self.sm, self.ss, self.am, self.as_ = self.cfg.stat_arrays()
        coeff = self.cfg.temporal_ensemble_coeff
        self.blend = TemporalEnsembler(self.cfg.chunk_size, coeff) if coeff is not None else None
        self.chunks = ChunkRunner(self.cfg.chunk_size)
        self.reset(None)

    def reset(self, ctx: EpisodeContext | None) -> list:
        if self.blend is not None:
            self.blend.reset()
        self.chunks.reset()
        self.t, self.idle, self.last = 0, 0, None
        return []

    def after_correction(self, obs: Observation, executed: bool = True, step: int | None = None) -> None:
        """A correction moved the arm: chunks predicted before it no longer apply, and the policy resumes the task
        from the corrected state in a new attempt (a fresh tick budget): the same fresh start as an episode's."""
        self.reset(None)

    def _chunk(self, obs: Observation) -> np.ndarray:
        from sim_backends.policies.openvla_client import proprio_vector

        size = self.cfg.image_size
        views = []
        for c in self.cfg.cameras:
            if c not in obs.images:
                raise PolicyError(
                    f"act: the checkpoint needs camera view {c!r}; the backend renders {list(obs.images)}"
                )
            img = np.asarray(obs.images[c], np.uint8)
            views.append(
                img if img.shape[:2] == (size, size) else cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)
            )
        t = self.torch
        images = t.from_numpy(np.stack(views)).permute(0, 3, 1, 2).float()[None].to(self.device) / 255.0
        state = t.from_numpy((proprio_vector(obs.state) - self.sm) / self.ss)[None].to(self.device)
        return self.model.predict(images, state)[0].cpu().numpy() * self.as_ + self.am

    def act(self, obs: Observation) -> Action | None:
        if self.t >= self.max_ticks:
            return None
        if self.blend is not None:
            vec = self.blend(self._chunk(obs))
        else:
            vec = self.chunks(self._chunk(obs) if self.chunks.needs_query() else None)
        self.t += 1
        a = Action(tuple(map(float, vec[:3])), matrix_to_quat(from_rot6d(vec[3:9])), int(vec[9] > 0.5), self.speed)
        self.idle = self.idle + 1 if still(a, self.last) else 0
        self.last = a
        return None if self.idle_stop and self.idle >= self.idle_stop else a

    def info(self) -> dict[str, Any]:
        return {"ticks": self.t}
