"""The `FailureSource` interface that every simulator backend implements.

The generator (data/generate.py) drives a backend only through this API:

    src = make_backend("pybullet", cameras=..., image_size=...)
    src.reset(scenario, seed, variant)          # task variant from a seed
    nominal = src.scripted_keyframes()          # the task's keyframes
    ep = src.execute(keyframes, physics_events) # run, render, label
    src.close()

`reset` must make the initial state a pure function of (scenario, seed,
variant) so that a failure episode and its paired success episode start from
the identical state.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, Sequence

from sim_backends.perturbations.physics import PhysicsEvent
from sim_backends.types import Episode, Keyframe


class FailureSource(ABC):
    name: str = "abstract"

    @abstractmethod
    def scenarios(self) -> list[str]:
        """Names of the task scenarios this backend can run."""

    @abstractmethod
    def scenario_info(self, scenario: str) -> dict[str, Any]:
        """Template, atomic actions, horizon and perturbation spec of a scenario."""

    @abstractmethod
    def reset(self, scenario: str, seed: int, variant: str = "seen") -> None:
        """Build the scene of `scenario` with objects/layout drawn from `seed`."""

    @abstractmethod
    def scripted_keyframes(self) -> list[Keyframe]:
        """The nominal (successful) keyframes for the current scene."""

    @abstractmethod
    def object_positions(self) -> dict[str, tuple[float, float, float]]:
        """Named object/zone positions, for semantic target substitution."""

    @abstractmethod
    def execute(self, keyframes: Sequence[Keyframe], physics_events: Sequence[PhysicsEvent] = ()) -> Episode:
        """Run keyframes from the state set by the last `reset`, render and label."""

    def close(self) -> None:  # noqa: B027 - optional hook
        pass

    def __enter__(self) -> "FailureSource":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
