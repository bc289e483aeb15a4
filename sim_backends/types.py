"""Core data types shared by every simulator backend.

A manipulation skill is a sequence of sparse keyframes tau = {(T_i, g_i, o_i)}
(paper, LabRobFail-Sim): T_i in SE(3) is the end-effector target pose, g_i in
{0, 1} the gripper command (1 = closed) and o_i the interaction target.
An `Episode` is what a backend returns after executing keyframes: images at
every executed keyframe from every camera, a state trace sampled at its own rate,
and labels derived from that trace.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from sim_backends.schema import TaskMeta

WRIST = "wrist"  # the hand camera's view name in every backend (`backend_kwargs.wrist=true` adds it)


def quat_to_matrix(q: tuple[float, float, float, float]) -> np.ndarray:
    """Rotation matrix of a unit quaternion in (x, y, z, w) order (PyBullet's)."""
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(m: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w) of a rotation matrix (Shepperd's method)."""
    t = float(np.trace(m))
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s)
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k]) * 2
        v = [0.0, 0.0, 0.0]
        v[i] = 0.25 * s
        v[j] = (m[j, i] + m[i, j]) / s
        v[k] = (m[k, i] + m[i, k]) / s
        q = (v[0], v[1], v[2], (m[k, j] - m[j, k]) / s)
    n = math.sqrt(sum(c * c for c in q))
    return tuple(float(c / n) for c in q)  # type: ignore[return-value]


def rotation_angle(q1: tuple[float, ...], q2: tuple[float, ...]) -> float:
    """Geodesic angle in radians between two unit quaternions."""
    d = abs(sum(a * b for a, b in zip(q1, q2)))
    return 2.0 * math.acos(min(1.0, d))


@dataclass
class Keyframe:
    """One sparse keyframe (T_i, g_i, o_i) plus bookkeeping for labels.

    `segment` indexes the task step (atomic action) the keyframe belongs to;
    `action` is that step's atomic action; `name` is a stable id within the task
    (used by the labeler to compare the executed plan with the nominal one).
    """

    name: str
    pos: tuple[float, float, float]
    quat: tuple[float, float, float, float]
    gripper: int
    target: str
    segment: int
    action: str
    speed: float = 0.4  # m/s of the Cartesian interpolation towards this keyframe
    settle_steps: int = 0  # extra physics steps once reached (grasp closure, release)

    @property
    def rotation(self) -> np.ndarray:
        return quat_to_matrix(self.quat)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Keyframe":
        return cls(**{**d, "pos": tuple(d["pos"]), "quat": tuple(d["quat"])})


@dataclass
class Labels:
    """Ground truth derived from simulator state (never from the perturbation)."""

    success: bool
    failure_type: str | None = None
    category: int | None = None  # taxonomy.Category value
    severity: int | None = None  # taxonomy.Severity value
    failure_keyframe: int | None = None  # 0-based index into the executed keyframes: the onset keyframe
    evidence: str = ""  # the state signal that decided the label, for auditing
    # the onset in sim time: the first trace sample where the labeled failure's state signature shows (seconds
    # since the trace began); the onset keyframe is `failure_keyframe`, the one that sample falls in
    onset_s: float | None = None

    @property
    def explained(self) -> bool:
        """False for a failure that no detector explains (it has no type and never enters a dataset)."""
        return self.success or self.failure_type is not None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class Episode:
    """A rendered, labeled trajectory as produced by a `FailureSource`."""

    episode_id: str
    backend: str
    task: str
    scenario: str
    variant: str
    seed: int
    pair_id: str
    role: str  # "nominal" or "injected"
    actions: list[str]  # ordered atomic actions of the task (Q1 ground truth)
    horizon: str
    nominal_keyframes: list[Keyframe]
    executed_keyframes: list[Keyframe]
    camera_names: list[str]
    images: list[list[bytes]]  # [view][keyframe] PNG bytes
    state_trace: dict[str, Any]  # column name -> samples, plus kf_end and rate_hz (sim_backends/schema.py)
    labels: Labels
    task_meta: TaskMeta  # what the labeler needs besides the trace (JSON in a shard: TaskMeta.to_json())
    perturbation: dict[str, Any] = field(default_factory=dict)  # provenance only
    # [view][keyframe]: view + projection matrix (16 + 16 floats) of each rendered image, None where the image was
    # not rendered or the backend cannot say (FailureSource.camera_matrices)
    cameras: list[list[list[float] | None]] = field(default_factory=list)
