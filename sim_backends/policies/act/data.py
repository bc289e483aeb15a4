"""Demonstrations for ACT: the backend's successful scripted episodes, recorded at the control rate.

Each plan keyframe is split into control ticks of at most `max_dist` metres / `max_angle` radians (the
target slides from the previous one), plus hold ticks where the plan lets the scene settle (a pour's tilt,
a press). Before each tick the recorder keeps what the policy will see (every camera view, the proprio
vector) and the tick's target as the action (position, rotation 6-D, gripper). Ticks go through the same
`FailureSource.step` as the supervised loop's actions, with the same settling on a gripper change, so a
trained policy replays them in the same conditions. Only episodes the task family judges successful are kept.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from labrobfail_vlm.augment import Augment, AugmentConfig
from sim_backends.policies.act.configuration_act import ACTConfig
from sim_backends.policies.act.modeling_act import AUX_SCALE
from sim_backends.source import FailureSource
from sim_backends.types import Keyframe, matrix_to_quat, quat_to_matrix, rotation_angle

MISS_MIN = 0.03  # m: the smallest grasp miss of a regrasp demonstration (closer ones often still catch the vessel)

HOLD_STEPS = 12  # physics steps one hold tick stands for (a tick is >= 8 steps)


def rot6d(r: np.ndarray) -> np.ndarray:
    """The first two columns of a rotation matrix (a continuous rotation representation)."""
    return np.concatenate([r[:, 0], r[:, 1]])


def from_rot6d(v: np.ndarray) -> np.ndarray:
    """Gram-Schmidt back to a rotation matrix."""
    a, b = np.asarray(v[:3], float), np.asarray(v[3:6], float)
    c0 = a / max(np.linalg.norm(a), 1e-8)
    b = b - c0 * float(np.dot(c0, b))
    c1 = b / max(np.linalg.norm(b), 1e-8)
    return np.stack([c0, c1, np.cross(c0, c1)], 1)


def action_vector(pos: Any, quat: Any, gripper: int) -> np.ndarray:
    return np.array([*pos, *rot6d(quat_to_matrix(tuple(quat))), float(gripper)], np.float32)


def grip_settle(gripper: int, current: int) -> int:
    """Settling physics steps for a gripper command (the supervised loop gives unnamed actions the same)."""
    return 0 if int(gripper) == int(current) else (50 if gripper else 40)


def ticks(
    pos0: np.ndarray, quat0: tuple, kf: Keyframe, max_dist: float, max_angle: float, gripper_change: bool = False
) -> list[tuple]:
    """Targets sliding from (pos0, quat0) to the keyframe, then hold ticks for its settling time (a gripper
    change settles within its own tick, see `grip_settle`)."""
    import pybullet as p  # slerp only; recording drives a simulator anyway

    dist = float(np.linalg.norm(np.asarray(kf.pos) - pos0))
    n = max(1, math.ceil(max(dist / max_dist, rotation_angle(quat0, kf.quat) / max_angle)))
    out = [
        (tuple(pos0 + (np.asarray(kf.pos) - pos0) * i / n), tuple(p.getQuaternionSlerp(quat0, kf.quat, i / n)))
        for i in range(1, n + 1)
    ]
    holds = 0 if gripper_change else kf.settle_steps // HOLD_STEPS
    return out + [out[-1]] * holds


def regrasp_start(src: FailureSource, plan: list[Keyframe], miss: float, rng: np.random.Generator) -> int | None:
    """Miss the plan's first grasp, then correct it as a supervisor would; the plan index to record from.

    The grasp step's keyframes (those of the first closing keyframe's segment, up to it) run shifted in the plane
    by MISS_MIN..`miss` metres in a random direction, so the fingers close beside the vessel; then the paper's P4
    correction for a misaligned grasp (its own instruction text, through the primitive mapper and executor the
    supervised loop uses) opens, re-centres on the vessel and closes. The recording starts where the scripted
    policy's re-planning goes on (`resume_index`); None: the plan has no grasp or the correction could not run.
    Neither the miss nor the correction is recorded: the demonstration starts where a supervisor hands the
    policy back a corrected grasp, and shows it going on from there.
    """
    from labrobfail_vlm.actions import to_primitives
    from labrobfail_vlm.corrections import STRATEGIES
    from sim_backends.executor import CorrectionExecutor
    from sim_backends.policies.scripted import resume_index

    close = next((i for i, k in enumerate(plan) if k.gripper == 1), None)
    if close is None:
        return None
    angle, r = rng.uniform(0, 2 * math.pi), rng.uniform(MISS_MIN, max(miss, MISS_MIN))
    off = np.array([math.cos(angle) * r, math.sin(angle) * r, 0.0])
    for kf in plan[: close + 1]:
        shift = off if kf.segment == plan[close].segment else np.zeros(3)
        src.step(dataclasses.replace(kf, pos=tuple(np.asarray(kf.pos) + shift)))
    labels = src.task_meta([]).labels
    text = STRATEGIES["P4"][1].format(target=labels.get(plan[close].target, plan[close].target))
    res = CorrectionExecutor(src).run(to_primitives(text, list(labels.values())))
    return resume_index(plan, src.observe().state, res.step) if res.executed else None


def record_demo(
    src: FailureSource,
    nominal_filter: Any,
    success: Any,
    scenario: str,
    seed: int,
    variant: str,
    cameras: list[str],
    max_dist: float = 0.03,
    max_angle: float = 0.15,
    noise: float = 0.0,
    carry_noise: float = 0.0,
    miss: float = 0.0,
) -> dict[str, np.ndarray] | None:
    """One demonstration (images (T, V, H, W, 3) uint8, state (T, 9), action (T, 10)), or None if it failed.

    `noise` > 0 (metres) records DART-style corrections: a free move of the open hand (not the last one before
    the gripper closes) drifts off its line, reaching up to `noise` from its keyframe on each horizontal axis
    (drawn per keyframe from the demo's seed), while the recorded actions stay on the line and the next move
    starts from where the hand really is. A policy taught only on perfect approaches never sees itself off the
    line, so it cannot learn to come back (the wrist view shows the vessel off centre; the action re-centres it).
    `carry_noise` > 0 does the same for moves of the closed hand (carrying), except a move that ends where the
    next keyframe acts in place (a tilt, a release) and a keyframe that acts in place itself: the pour is made
    exactly over the destination, and the demonstration shows the way back onto the line before it.
    `miss` > 0 (metres) records a demonstration that starts from a corrected grasp (`regrasp_start`).
    """
    from sim_backends.policies.openvla_client import proprio_vector

    src.reset(scenario, seed, variant)
    plan = nominal_filter(src.scripted_keyframes())
    src.begin()
    rng = np.random.default_rng(seed)
    start = regrasp_start(src, plan, miss, rng) if miss > 0 else 0
    if start is None:
        src.finish()
        return None
    s = src.observe().state
    pos, quat, grip = np.asarray(s["ee_pos"], float), tuple(s["ee_quat"]), int(s["grip_cmd"])
    images, states, actions = [], [], []
    for i, kf in enumerate(plan[start:], start):
        nxt = plan[i + 1] if i + 1 < len(plan) else None
        free = noise > 0 and kf.gripper == grip == 0 and nxt is not None and nxt.gripper == 0
        carrying = (
            carry_noise > 0
            and kf.gripper == grip == 1
            and nxt is not None
            and nxt.gripper == 1
            and not np.allclose(kf.pos, pos)  # this keyframe moves the hand ...
            and not np.allclose(nxt.pos, kf.pos)  # ... and the next one does not act where it ends
        )
        size = noise if free else carry_noise if carrying else 0.0
        off = np.append(rng.uniform(-size, size, 2), 0.0) if size else np.zeros(3)
        line = ticks(pos, quat, kf, max_dist, max_angle, kf.gripper != grip)
        for j, (tp, tq) in enumerate(line):
            obs = src.observe()
            images.append(np.stack([obs.images[c] for c in cameras]))
            states.append(proprio_vector(obs.state))
            actions.append(action_vector(tp, tq, kf.gripper))
            src.step(
                Keyframe(
                    kf.name,
                    tuple(np.asarray(tp) + off * (j + 1) / len(line)),
                    tq,
                    kf.gripper,
                    kf.target,
                    kf.segment,
                    kf.action,
                    kf.speed,
                    grip_settle(kf.gripper, grip),
                )
            )
            grip = kf.gripper
        pos, quat = np.asarray(kf.pos, float) + off, tuple(kf.quat)
    ep = src.finish()
    if not success(ep):
        return None
    return {"images": np.stack(images), "state": np.stack(states), "action": np.stack(actions)}


def close_tick(action: np.ndarray) -> int | None:
    """The first tick of a demonstration that commands the fingers closed (0 when it starts holding, as a regrasp
    demonstration does), or None when it never closes them."""
    closed = np.nonzero(action[:, 9] > 0.5)[0]
    return int(closed[0]) if len(closed) else None


def key_points(action: np.ndarray) -> np.ndarray:
    """(AUX_POINTS, 3): the target position where a demonstration first commands the fingers closed (`close_tick`;
    its first tick when it never does) and where its hand is turned furthest from its first orientation (a pour's
    tilt). Read from the recorded actions, which come from the scripted plan on simulator state: the ACT's auxiliary
    targets (modeling_act.py)."""
    grasp = action[close_tick(action) or 0, :3]
    q0 = matrix_to_quat(from_rot6d(action[0, 3:9]))
    turned = [rotation_angle(q0, matrix_to_quat(from_rot6d(a[3:9]))) for a in action]
    return np.stack([grasp, action[int(np.argmax(turned)), :3]]).astype(np.float32)


def normalisation(demos: list[dict[str, np.ndarray]]) -> dict[str, list[float]]:
    st = np.concatenate([d["state"] for d in demos])
    ac = np.concatenate([d["action"] for d in demos])
    std = lambda x: np.maximum(x.std(0), 1e-3)  # noqa: E731 - constant columns (the gripper) stay finite
    return {
        "state_mean": st.mean(0).tolist(),
        "state_std": std(st).tolist(),
        "action_mean": ac.mean(0).tolist(),
        "action_std": std(ac).tolist(),
    }


class DemoDataset(Dataset):
    """(images, state, action chunk, padding, key points) at every step of every demonstration, normalised; the
    key points (`key_points`) relative to the hand, in AUX_SCALE metres.

    With `augment`, every sample's views are shifted, zoomed and recoloured by a fresh draw (the project's grid
    augmentation, one affine per view): the cameras stand elsewhere in every episode of the wide world, so where a
    vessel lies in the picture says where it stands only relative to the hand, and the draw keeps the policy from
    learning absolute pixel positions of its few hundred demonstrations.

    With `hold_end`, a chunk that runs past its demonstration's end is taught to hold the last target (the scripted
    plan stands still there) instead of being masked out: ACT has no stop signal but standing still (`idle_stop`),
    and a policy never shown the end of a task keeps moving after it, undoing what it did (docs/EXPERIMENTS.md,
    28 Nov: the pour ACT set the beaker back, then pushed it 14 cm away)."""

    def __init__(
        self,
        demos: list[dict[str, np.ndarray]],
        cfg: ACTConfig,
        augment: AugmentConfig | None = None,
        seed: int = 0,
        hold_end: bool = False,
    ):
        self.demos, self.k, self.hold_end = demos, cfg.chunk_size, hold_end
        self.augment, self.rng = augment, np.random.default_rng(seed)
        self.index = [(i, t) for i, d in enumerate(demos) for t in range(len(d["action"]))]
        self.points = [key_points(np.asarray(d["action"])) for d in demos]
        self.sm, self.ss, am, as_ = cfg.stat_arrays()
        self.am, self.as_ = am.astype(np.float32), as_.astype(np.float32)  # float32 targets, as the model computes

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, j: int) -> tuple[torch.Tensor, ...]:
        i, t = self.index[j]
        d = self.demos[i]
        n = len(d["action"])
        idx = np.minimum(np.arange(t, t + self.k), n - 1)  # past the end: repeat the last action (masked out, or held)
        views = d["images"][t]
        if self.augment is not None:
            aug = Augment.draw(self.augment, len(views), self.rng)
            views = np.stack([aug.image(v, k) for k, v in enumerate(views)])
        img = torch.from_numpy(views).permute(0, 3, 1, 2).float() / 255.0
        state = torch.from_numpy((d["state"][t] - self.sm) / self.ss)
        act = torch.from_numpy((d["action"][idx] - self.am) / self.as_)
        pad = torch.from_numpy((np.arange(t, t + self.k) >= n) & (not self.hold_end))
        hand = np.asarray(d["state"][t][:3], np.float32)  # proprio_vector: ee_pos first
        points = torch.from_numpy((self.points[i] - hand) / AUX_SCALE)
        return img, state, act, pad, points
