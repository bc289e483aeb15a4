"""Control-level perturbations Phi_ctrl (paper Eq. 1), backend-agnostic.

p~_i = p_i + xi_trans and R~_i = R_i Exp(xi_rot) with xi ~ N(0, Sigma), Sigma = diag(sigma^2);
each gripper command (open or closed) corrupted with probability lambda_grip; premature
termination of the keyframe sequence (the controller stops early).
Each operator returns a new keyframe list and never mutates its input, and a provenance record.

`min_norm` (a perturbation option, 0 = off) is a rejection filter on top of the paper's draw: a noise
vector shorter than it is redrawn. It is named in the task configs and every record counts the draws it
rejected (`rejected`), so a manifest can say how far the kept draws are from N(0, Sigma).
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


MAX_REJECTIONS = 1000  # a min_norm the sigma can hardly reach keeps its last draw rather than looping


def gaussian_noise(rng: np.random.Generator, sigma: Sequence[float], min_norm: float = 0.0) -> tuple[np.ndarray, int]:
    """xi ~ N(0, diag(sigma^2)); with `min_norm` > 0, redrawn while ||xi|| < min_norm. Returns (xi, rejected)."""
    sig = np.asarray(sigma, float)
    for rejected in range(MAX_REJECTIONS):
        xi = rng.normal(0.0, 1.0, size=3) * sig
        if float(np.linalg.norm(xi)) >= min_norm:
            return xi, rejected
    return xi, MAX_REJECTIONS


def translate(
    kfs: Sequence[Keyframe],
    names: Sequence[str],
    sigma: Sequence[float],
    rng: np.random.Generator,
    min_norm: float = 0.0,
) -> tuple[list[Keyframe], dict]:
    """Add one Gaussian offset to the positions of the named keyframes (one faulty estimate)."""
    xi, rejected = gaussian_noise(rng, sigma, min_norm)
    out = list(kfs)
    for i in _indices(kfs, names):
        p = np.asarray(out[i].pos) + xi
        out[i] = dataclasses.replace(out[i], pos=tuple(float(v) for v in p))
    return out, {
        "op": "translate",
        "keyframes": list(names),
        "xi_trans": xi.round(5).tolist(),
        "min_norm": min_norm,
        "rejected": rejected,
    }


def rotate(
    kfs: Sequence[Keyframe],
    names: Sequence[str],
    sigma: Sequence[float],
    rng: np.random.Generator,
    min_norm: float = 0.0,
) -> tuple[list[Keyframe], dict]:
    """R~ = R Exp(xi_rot) on the named keyframes (xi in the body frame)."""
    xi, rejected = gaussian_noise(rng, sigma, min_norm)
    dR = so3_exp(xi)
    out = list(kfs)
    for i in _indices(kfs, names):
        out[i] = dataclasses.replace(out[i], quat=matrix_to_quat(out[i].rotation @ dR))
    return out, {
        "op": "rotate",
        "keyframes": list(names),
        "xi_rot": xi.round(5).tolist(),
        "min_norm": min_norm,
        "rejected": rejected,
    }


def corrupt_gripper(
    kfs: Sequence[Keyframe], names: Sequence[str], lam: float, rng: np.random.Generator
) -> tuple[list[Keyframe], dict]:
    """Each gripper command among the named keyframes, closed or open, is inverted with probability lambda_grip.

    A command that was corrupted stays corrupted on the following keyframes of the same segment (an actuator
    fault, not a one-step glitch): fingers that failed to close stay open, fingers that failed to open stay
    shut. Every named keyframe is one Bernoulli(lambda) trial, in plan order; one already overwritten by an
    earlier fault of its segment is not drawn again. `flipped` records each fault as {keyframe, to}.
    """
    if not 0.0 <= lam <= 1.0:
        raise ValueError(f"corrupt_gripper: lambda must be in [0, 1], got {lam}")
    out = list(kfs)
    flipped: list[dict[str, str]] = []
    faulty: set[int] = set()
    for i in _indices(kfs, names):
        if i in faulty or rng.random() >= lam:
            continue
        to = 1 - out[i].gripper
        seg = out[i].segment
        for j in range(i, len(out)):
            if out[j].segment != seg:
                break
            out[j] = dataclasses.replace(out[j], gripper=to)
            faulty.add(j)
        flipped.append({"keyframe": out[i].name, "to": "closed" if to else "open"})
    return out, {"op": "corrupt_gripper", "keyframes": list(names), "lambda": lam, "flipped": flipped}


def truncate(kfs: Sequence[Keyframe], names: Sequence[str], rng: np.random.Generator) -> tuple[list[Keyframe], dict]:
    """Stop the motion before one of the named keyframes; the arm then holds still.

    The remaining keyframes are replaced by copies of the last reached pose, so
    the rendered trajectory keeps its length and shows a motionless arm.
    """
    cut = int(rng.choice(_indices(kfs, names)))
    hold = kfs[cut - 1] if cut > 0 else kfs[0]
    out = list(kfs[:cut]) + [
        dataclasses.replace(k, pos=hold.pos, quat=hold.quat, gripper=hold.gripper) for k in kfs[cut:]
    ]
    return out, {"op": "truncate", "cut_before": kfs[cut].name}
