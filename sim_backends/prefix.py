"""Prefix reuse: a pair's injected run starts from its nominal run's saved state where the two plans part.

The stepping contract (source.FailureSource) calls these hooks; a backend that can save and restore its world
(PyBullet's `physics: prefix` preset) implements `_checkpoint`, `_rewind`, `_release` and `_world_clean` and turns
`reuse_prefix` on. Off, nothing here runs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Iterable, Sequence

from sim_backends.perturbations.physics import PhysicsEvent
from sim_backends.types import Keyframe

if TYPE_CHECKING:
    from sim_backends.source import _Run


@dataclass
class Prefix:
    """An open-loop run recorded for prefix reuse: the saved state before each of its keyframes, and its images.

    A pair's injected run repeats its nominal run's keyframes up to the first one the perturbation changes (or a
    physics event fires at). With `reuse_prefix` on, `reset()` of the same (scenario, seed, variant) rewinds the
    world to the recorded start instead of rebuilding it, and the next `execute` rewinds to the state before the
    first keyframe that differs (the latest saved state at or before it) and copies the images before it. A saved
    state may not restore everything the simulator carries from step to step (PyBullet's: the joint motors' last
    torques), so the continuation may differ a little from a fresh run's (a physics preset of its own, checked like one:
    scripts/check_physics.py). Only a run told which run follows it (`execute(then=...)`) is recorded, and it saves
    only the state that run restarts from (a saved state costs about 3 ms in a lab scene); any other run after the
    rewind finds the world rebuilt, as `reset` alone builds it."""

    key: tuple[str, int, str]
    then: tuple[list[Keyframe], list[PhysicsEvent]]  # the run the recording is for
    keyframes: list[Keyframe]
    render: set[int] | None
    checkpoints: dict[int, Any]
    images: list[list[bytes]]
    cameras: list[list[list[float] | None]]
    armed: bool = False  # reset() rewound the world to checkpoint 0: the next execute() may fast-forward


def shared_prefix(
    a: Sequence[Keyframe], a_render: set[int] | None, b: Sequence[Keyframe], b_render: set[int] | None, events=()
) -> int:
    """How many leading keyframes a run of `b` under `events` can take from a run of `a`: the same keyframes, no
    event before them, the same of them rendered, and never the last one (a backend may draw the last keyframe
    again after the settling)."""
    k, limit = 0, min(len(a) - 1, len(b) - 1, *(e.at_keyframe for e in events))
    while k < limit and a[k] == b[k]:
        k += 1
    below = lambda r: None if r is None else {i for i in r if i < k}  # noqa: E731
    while k > 0 and below(a_render) != below(b_render):
        k -= 1
    return max(k, 0)


class PrefixReuse:
    """The hooks and book-keeping of prefix reuse, mixed into FailureSource."""

    reuse_prefix: bool = False  # off unless a backend that can save and restore its state turns it on
    _prefix: Prefix | None
    _key: tuple[str, int, str]

    def _checkpoint(self) -> Any:
        """The simulator's state now, to `_rewind` to (backends with `reuse_prefix`)."""
        raise NotImplementedError("this backend has no prefix reuse")

    def _rewind(self, checkpoint: Any) -> None:
        """Put the world back in a state `_checkpoint` saved during the recorded run, as the run saw it then."""
        raise NotImplementedError("this backend has no prefix reuse")

    def _release(self, checkpoints: Iterable[Any]) -> None:  # noqa: B027 - optional hook
        """Free saved states that will not be rewound to."""

    def _world_clean(self) -> bool:
        """Whether the world since the recorded run began holds only what its checkpoints restore."""
        return True

    def _picks(self, keyframes: Sequence[Keyframe]) -> set[int] | None:
        """The keyframes an open-loop run of `keyframes` renders (FailureSource's)."""
        raise NotImplementedError

    def _drop_prefix(self) -> None:
        if self._prefix is not None:
            self._release(self._prefix.checkpoints.values())
            self._prefix = None

    def _rewound_for(self, key: tuple[str, int, str]) -> bool:
        """reset(): rewind to the recorded run's start instead of rebuilding, when it was recorded from this key's
        world and nothing since changed what a saved state does not hold (then kept for the planned run only; the
        recorder rewinds too, so what a backend reads between reset and begin is the initial state's)."""
        pre = self._prefix
        if pre is not None and pre.key == key and not pre.armed and self._world_clean():
            self._rewind(pre.checkpoints[0])
            pre.armed = True
            return True
        self._drop_prefix()
        return False

    def _planned(self, keyframes: Sequence[Keyframe], events: Sequence[PhysicsEvent]) -> Prefix | None:
        """The recording made for this run, taken out of the source (begin() rebuilds a world rewound for another
        run), or None."""
        pre = self._prefix
        if pre is None or not pre.armed or pre.then != (list(keyframes), list(events)):
            return None
        self._prefix = None
        return pre

    def _fast_forward(
        self, pre: Prefix, run: _Run, keyframes: Sequence[Keyframe], events: Sequence[PhysicsEvent]
    ) -> int:
        """Rewind to the latest saved state before the first keyframe this run does not share with the recorded
        one, take the recorded images and camera matrices before it, free the recording. Returns that keyframe."""
        k = shared_prefix(pre.keyframes, pre.render, keyframes, run.render, events)
        k = max(i for i in pre.checkpoints if i <= k)
        if k:
            self._rewind(pre.checkpoints[k])
            run.executed = list(keyframes[:k])
            run.images = [list(v[:k]) for v in pre.images]
            run.cameras = [list(c[:k]) for c in pre.cameras]
        self._release(pre.checkpoints.values())
        return k

    def _start_recording(
        self,
        run: _Run,
        keyframes: Sequence[Keyframe],
        events: Sequence[PhysicsEvent],
        then: tuple[Sequence[Keyframe], Sequence[PhysicsEvent]] | None,
    ) -> bool:
        """Save the state now and, as the run goes, before the first keyframe `then`'s run will not share, when
        `reuse_prefix` is on, the next run's plan is known and this run changes no physics. Returns whether the run
        is recorded."""
        self._drop_prefix()
        if not self.reuse_prefix or then is None or events:
            return False
        run.checkpoints = {0: self._checkpoint()}
        run.keep = {shared_prefix(keyframes, run.render, then[0], self._picks(then[0]), then[1])}
        return True
