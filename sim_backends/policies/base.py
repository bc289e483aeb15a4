"""The policy interface (observation -> end-effector action), the episode context and the policy registry.

A policy sees what a robot's controller would: `Observation` (one image per camera view and the latest
state sample: ee_pos, ee_quat, width, grip_cmd, ...) and answers an `Action`, an end-effector target
(position, orientation, gripper). The supervision loop (sim_backends/supervision/loop.py) turns each action into a
keyframe of the backend's stepping contract. Policies register by name:

    @register_policy("scripted")
    class ScriptedPolicy(Policy): ...
    make_policy("act", checkpoint="outputs/act/final")   # imports sim_backends.policies.act.policy on first use
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any

from labrobfail_vlm.registry import Registry
from sim_backends.perturbations.physics import PhysicsEvent
from sim_backends.source import Observation
from sim_backends.types import Keyframe

POLICIES = Registry(
    "policy",
    lazy={
        "scripted": "sim_backends.policies.scripted",
        "act": "sim_backends.policies.act.policy",
        "openvla": "sim_backends.policies.openvla_client",
    },
)
register_policy, make_policy = POLICIES.register, POLICIES.make  # lazy: imported on first use


class PolicyError(RuntimeError):
    """The policy cannot produce an action now (a server that fails, times out or answers garbage): the
    loop ends that trial with this message and goes on with the next one."""


@dataclass
class Action:
    """An end-effector target. `name` is the plan keyframe it belongs to when the policy knows it (the
    scripted policy); otherwise the loop assigns one by progress along the plan (sim_backends/supervision/loop.py)."""

    pos: tuple[float, float, float]
    quat: tuple[float, float, float, float]  # x, y, z, w
    gripper: int  # 1 = closed
    speed: float = 0.25  # m/s of the move towards the target
    settle: int = 0  # extra physics steps once there (a gripper change needs time to close)
    name: str | None = None

    @classmethod
    def from_keyframe(cls, kf: Keyframe) -> "Action":
        return cls(kf.pos, kf.quat, kf.gripper, kf.speed, kf.settle_steps, kf.name)


@dataclass
class EpisodeContext:
    """What a policy and a supervisor know about the episode before it starts."""

    backend: str
    scenario: str
    seed: int
    variant: str
    instruction: str  # the task in words
    nominal: list[Keyframe]  # the plan (the family's first `steps` steps only, e.g. "pick")
    positions: dict[str, tuple[float, float, float]]  # object homes and zones (target substitution)
    perturbations: list[dict[str, Any]]  # the scenario's failure-injection specs
    objects: list[str]  # the scene's object and place names (corrections name them)
    camera_names: list[str] = field(default_factory=list)
    goals: list[dict[str, Any]] | None = None  # the family's success goals when they replace the task's


class Policy(ABC):
    name = "abstract"

    def reset(self, ctx: EpisodeContext) -> list[PhysicsEvent]:
        """Start an episode; returns physics events to fire during it (only the scripted policy injects)."""
        return []

    @abstractmethod
    def act(self, obs: Observation) -> Action | None:
        """The next target, or None when the policy is done."""

    def after_correction(  # noqa: B027 - optional hook
        self, obs: Observation, executed: bool = True, step: int | None = None
    ) -> None:
        """Called when a correction has run (`executed`: all of it; else it stopped early or was refused) and
        control returns to the policy; `step`: the plan step the correction redid last, if any."""

    def info(self) -> dict[str, Any]:
        """What the log records about this episode's policy (e.g. the injected perturbation)."""
        return {}

    def close(self) -> None:  # noqa: B027 - optional hook
        pass
