"""Control-level perturbations Phi_ctrl (paper Eq. 1), backend-agnostic.

p~_i = p_i + xi_trans and R~_i = R_i Exp(xi_rot) with xi ~ N(0, Sigma);
gripper commands corrupted with probability lambda_grip; premature
termination of the keyframe sequence (the controller stops early).
Each operator returns a new keyframe list and never mutates its input.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numpy as np

from sim_backends.types import Keyframe, matrix_to_quat


def so3_exp(xi: np.ndarray) -> np.ndarray:
    """Exponential map so(3) -> SO(3) (Rodrigues' formula)."""
    theta = float(np.linalg.norm(xi))
    if theta < 1e-12:
        return np.eye(3)
    k = xi / theta
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(theta) * K + (1 - math.cos(theta)) * (K @ K)


def _indices(kfs: Sequence[Keyframe], names: Sequence[str]) -> list[int]:
    idx = [i for i, k in enumerate(kfs) if k.name in set(names)]
    if not idx:
        raise ValueError(f"perturbation names keyframes {list(names)} that the task does not have")
    return idx


def _sample_min_norm(rng: np.random.Generator, sigma: np.ndarray, min_norm: float) -> np.ndarray:
    """xi ~ N(0, diag(sigma^2)), resampled until ||xi|| >= min_norm (rejection keeps it Gaussian-shaped)."""
    for _ in range(1000):
        xi = rng.normal(0.0, 1.0, size=3) * sigma
        if float(np.linalg.norm(xi)) >= min_norm:
            return xi
    return xi


def translate(kfs: Sequence[Keyframe], names: Sequence[str], sigma: Sequence[float], rng: np.random.Generator,
              min_norm: float = 0.0) -> tuple[list[Keyframe], dict]:
    """Add one Gaussian offset to the positions of the named keyframes (one faulty estimate)."""
    xi = _sample_min_norm(rng, np.asarray(sigma, float), min_norm)
    out = list(kfs)
    for i in _indices(kfs, names):
        p = np.asarray(out[i].pos) + xi
        out[i] = dataclasses.replace(out[i], pos=tuple(float(v) for v in p))
    return out, {"op": "translate", "keyframes": list(names), "xi_trans": xi.round(5).tolist()}


def rotate(kfs: Sequence[Keyframe], names: Sequence[str], sigma: Sequence[float], rng: np.random.Generator,
           min_norm: float = 0.0) -> tuple[list[Keyframe], dict]:
    """R~ = R Exp(xi_rot) on the named keyframes (xi in the body frame)."""
    xi = _sample_min_norm(rng, np.asarray(sigma, float), min_norm)
    dR = so3_exp(xi)
    out = list(kfs)
    for i in _indices(kfs, names):
        out[i] = dataclasses.replace(out[i], quat=matrix_to_quat(out[i].rotation @ dR))
    return out, {"op": "rotate", "keyframes": list(names), "xi_rot": xi.round(5).tolist()}


def corrupt_gripper(kfs: Sequence[Keyframe], names: Sequence[str], lam: float, rng: np.random.Generator
                    ) -> tuple[list[Keyframe], dict]:
    """Each closing command among the named keyframes stays open with probability lambda_grip.

    A command that was corrupted stays corrupted on the following keyframes of
    the same segment (an actuator fault, not a one-step glitch).
    """
    out = list(kfs)
    flipped: list[str] = []
    idx = _indices(kfs, names)
    for i in idx:
        if out[i].gripper == 1 and rng.random() < lam:
            seg = out[i].segment
            for j in range(i, len(out)):
                if out[j].segment != seg:
                    break
                out[j] = dataclasses.replace(out[j], gripper=0)
            flipped.append(out[i].name)
    return out, {"op": "corrupt_gripper", "keyframes": list(names), "lambda": lam, "flipped": flipped}


def truncate(kfs: Sequence[Keyframe], names: Sequence[str], rng: np.random.Generator) -> tuple[list[Keyframe], dict]:
    """Stop the motion before one of the named keyframes; the arm then holds still.

    The remaining keyframes are replaced by copies of the last reached pose, so
    the rendered trajectory keeps its length and shows a motionless arm.
    """
    cut = int(rng.choice(_indices(kfs, names)))
    hold = kfs[cut - 1] if cut > 0 else kfs[0]
    out = list(kfs[:cut]) + [dataclasses.replace(k, pos=hold.pos, quat=hold.quat, gripper=hold.gripper)
                             for k in kfs[cut:]]
    return out, {"op": "truncate", "cut_before": kfs[cut].name}
