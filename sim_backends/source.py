"""The `FailureSource` interface that every simulator backend implements: a stepping contract.

An episode is driven step by step, so that a policy, a supervisor or a correction can act
between steps (closed-loop supervision):

    src = make_backend("pybullet", cameras=..., image_size=...)
    src.reset(scenario, seed, variant)          # initial state: a pure function of the three
    nominal = src.scripted_keyframes()          # the task's keyframes
    src.begin(physics_events)                   # start recording the trace
    for kf in nominal:
        src.step(kf)                            # move from the current state to kf; images at its end
        obs = src.observe()                     # per-view images + the latest state sample, any time
        trace = src.trace_so_far()              # the state trace recorded so far
    ep = src.finish()                           # settle, then label once from the recorded trace
    src.close()

`execute(keyframes, events)` is exactly that loop. A correction is more keyframes stepped
from wherever the arm is (`step` never resets); a low-level action (a pose delta) becomes a
Keyframe relative to `observe().state["ee_pos"]`/`["ee_quat"]`. Labels are derived once, here in
`finish()`, from the recorded trace and the backend's `TaskMeta`; backends never label.
"""

from __future__ import annotations

import io
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from PIL import Image

from labrobfail_vlm.grid import sample_keyframes
from labrobfail_vlm.taxonomy import check_variant, horizon_of
from sim_backends.labeler import derive_labels
from sim_backends.perturbations.physics import PhysicsEvent
from sim_backends.prefix import Prefix, PrefixReuse
from sim_backends.schema import NON_SAMPLE, TaskMeta, Trace
from sim_backends.types import Episode, Keyframe


def png_bytes(img: np.ndarray) -> bytes:
    """PNG of an HxWx3 uint8 image (fast compression: shards are zstd-compressed again anyway)."""
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


@dataclass
class Observation:
    """What a policy or supervisor sees at one moment: one image per camera view and the state."""

    images: dict[str, np.ndarray]  # view name -> HxWx3 uint8
    state: dict[str, Any]  # the latest trace sample: column -> value (ee_pos, width, <obj>.pos, ...)
    keyframe: int  # number of keyframes executed so far


@dataclass
class _Run:
    """Book-keeping of the episode being recorded (between `begin` and `finish`)."""

    events: list[PhysicsEvent]
    executed: list[Keyframe] = field(default_factory=list)
    images: list[list[bytes]] = field(default_factory=list)  # [view][keyframe] PNG bytes (b"": not rendered)
    cameras: list[list[list[float] | None]] = field(default_factory=list)  # [view][keyframe]: see camera_matrices
    last: list[np.ndarray] | None = None  # images rendered at the end of the last step
    render: set[int] | None = None  # keyframe indices to render at the end of their step (None: every one)
    checkpoints: dict[int, Any] | None = None  # a recorded run's saved states: [k] before keyframe k (prefix.Prefix)
    keep: set[int] | None = None  # the k whose state a recorded run saves (None: every one)


class FailureSource(PrefixReuse, ABC):
    name: str = "abstract"
    # Open-loop `execute` renders only the keyframes that a keyframe grid of this many frames shows
    # (labrobfail_vlm.grid.sample_keyframes picks them from the keyframes' steps, known before the run);
    # the others hold b"" in `images`. None renders every keyframe. Rendering is most of an episode's cost
    # once physics is cheap, and a 16-frame grid shows 12 of an average 18 keyframes.
    render_frames: int | None = None

    def __init__(self) -> None:
        self._key: tuple[str, int, str] = ("", 0, "")
        self._fresh = False
        self._run: _Run | None = None
        self._prefix: Prefix | None = None

    # ---- configuration (class level: checked before any simulator starts) ---------------------------
    # the fixed views this backend renders (name -> its camera); empty: names checked only when a source is built
    CAMERAS: dict[str, Any] = {}

    @classmethod
    def check_cameras(cls, cameras: Sequence[str]) -> None:
        """ValueError naming the views this backend does not render, before any simulator starts (a run must not
        record a bad camera list in its run.json and then fail)."""
        unknown = [v for v in cameras if cls.CAMERAS and v not in cls.CAMERAS]
        if unknown:
            raise ValueError(f"cameras: unknown view(s) {unknown}; available: {', '.join(cls.CAMERAS)}")

    @classmethod
    def prepare_kwargs(cls, kwargs: dict[str, Any]) -> dict[str, Any]:
        """Check and resolve the backend's own config section (`backend_kwargs`); raise ValueError
        "<key>: <problem>" on a bad value. The default accepts the section as it is."""
        return dict(kwargs)

    @classmethod
    def unavailable(cls) -> str | None:
        """Why this backend cannot run on this machine at all (a missing device, not a missing package),
        or None. Tests skip a backend only for such a reason."""
        return None

    @classmethod
    def list_scenarios(cls, **kwargs: Any) -> list[str]:
        """Scenario names, without starting a simulator when the backend can (default: start one)."""
        src = cls(**kwargs)
        try:
            return src.scenarios()
        finally:
            src.close()

    @classmethod
    def scenario_repeats(cls, **kwargs: Any) -> dict[str, int]:
        """How many times each scenario appears per generation cycle (oversampling; default once each)."""
        return {s: 1 for s in cls.list_scenarios(**kwargs)}

    # ---- task description --------------------------------------------------------------------------
    @abstractmethod
    def scenarios(self) -> list[str]:
        """Names of the task scenarios this backend can run."""

    @abstractmethod
    def scenario_info(self, scenario: str) -> dict[str, Any]:
        """Template, perturbation spec and substitutes of a scenario."""

    @abstractmethod
    def scripted_keyframes(self) -> list[Keyframe]:
        """The nominal (successful) keyframes for the current scene."""

    @abstractmethod
    def object_positions(self) -> dict[str, tuple[float, float, float]]:
        """Named object/zone positions, for semantic target substitution."""

    def camera_matrices(self) -> list[list[float]] | None:
        """Per view, the view and projection matrices of its image now (OpenGL column-major, 16 + 16 floats), so
        a world point can be placed in the picture (the tower's position targets); None when the backend cannot
        say. Recorded beside every rendered image (`Episode.cameras`)."""
        return None

    @property
    @abstractmethod
    def camera_names(self) -> list[str]:
        """Views that `render` returns, in order (empty when the backend does not render)."""

    # ---- backend primitives (what a backend implements) --------------------------------------------
    @abstractmethod
    def _reset(self, scenario: str, seed: int, variant: str) -> None:
        """Build the scene of `scenario` with objects/layout drawn from `seed`."""

    @abstractmethod
    def _begin(self) -> None:
        """Start a new trace with the sample of the current (initial) state."""

    @abstractmethod
    def _apply_physics(self, event: PhysicsEvent) -> None:
        """Change a physical parameter now (Phi_phy), from the current state."""

    @abstractmethod
    def _move(self, kf: Keyframe, index: int) -> None:
        """Drive to `kf` from the current state, sampling the trace with program counter `index`;
        end with one sample at the reached pose and append its index to the trace's `kf_end`."""

    @abstractmethod
    def _settle(self) -> None:
        """Let the scene come to rest after the last keyframe (still sampling the trace)."""

    @abstractmethod
    def render(self) -> list[np.ndarray]:
        """One HxWx3 uint8 image per camera view of the current state."""

    def _settled_images(self) -> list[np.ndarray] | None:
        """After the settling: images that replace the last keyframe's when the settling changed what they must show
        (a backend drawing broken glass: a break in the settling). None (the default): the last images stand."""
        return None

    @abstractmethod
    def trace_so_far(self) -> Trace:
        """The state trace recorded since `begin` (a copy: columns, `kf_end`, `rate_hz`)."""

    @abstractmethod
    def task_meta(self, executed: Sequence[Keyframe]) -> TaskMeta:
        """The task metadata of the current scene, for an episode that executed `executed`."""

    # ---- the stepping contract ---------------------------------------------------------------------
    def reset(self, scenario: str, seed: int, variant: str = "seen") -> None:
        check_variant(variant)
        self._run = None
        key = (scenario, seed, variant)
        if not self._rewound_for(key):
            self._reset(scenario, seed, variant)
        self._fresh = True
        self._key = key

    def begin(self, physics_events: Sequence[PhysicsEvent] = (), render: set[int] | None = None) -> None:
        """Start recording an episode from the state `reset` built; `physics_events` fire before the
        keyframe whose index they name; `render`: the keyframe indices whose images are taken (None: all)."""
        if not self._fresh:
            raise RuntimeError("begin() needs a fresh reset(): every episode starts from the seeded initial state")
        if self._prefix is not None and self._prefix.armed:  # rewound for the planned run, and this is another
            self._drop_prefix()
            self._reset(*self._key)
        self._fresh = False
        self._run = _Run(
            list(physics_events),
            images=[[] for _ in self.camera_names],
            cameras=[[] for _ in self.camera_names],
            render=render,
        )
        self._begin()

    def step(self, kf: Keyframe) -> None:
        """Execute one keyframe from the current state; render every view at its end."""
        run = self._active()
        i = len(run.executed)
        for ev in run.events:
            if ev.at_keyframe == i:
                self._apply_physics(ev)
        self._move(kf, i)
        run.executed.append(kf)
        if run.checkpoints is not None and (run.keep is None or i + 1 in run.keep):
            run.checkpoints[i + 1] = self._checkpoint()
        if run.render is not None and i not in run.render:
            run.last = None  # observe() renders on demand
            for v, c in zip(run.images, run.cameras):
                v.append(b"")
                c.append(None)
            return
        run.last = self.render() if self.camera_names else []
        mats = self.camera_matrices() if run.last else None
        for v, img in enumerate(run.last):
            run.images[v].append(png_bytes(img))
            run.cameras[v].append(mats[v] if mats else None)

    def observe(self) -> Observation:
        """Images and state now; right after a step, its keyframe images (rendered once)."""
        run = self._active()
        imgs = run.last if run.last is not None else (self.render() if self.camera_names else [])
        trace = self.trace_so_far()
        state = {k: v[-1] for k, v in trace.items() if k not in NON_SAMPLE}
        return Observation(dict(zip(self.camera_names, imgs)), state, len(run.executed))

    def finish(self) -> Episode:
        """Settle the scene, then derive the labels once from the recorded trace and the task metadata."""
        run = self._active()
        self._settle()
        last, redrawn = len(run.executed) - 1, False
        if self.camera_names and last >= 0 and (run.render is None or last in run.render):
            if (imgs := self._settled_images()) is not None:
                mats = self.camera_matrices()  # a wrist view follows the hand, which may still have moved
                for v, img in enumerate(imgs):
                    run.images[v][last] = png_bytes(img)
                    run.cameras[v][last] = mats[v] if mats else None
                redrawn = True
        self._run = None
        trace = self.trace_so_far()
        if redrawn:  # readers of a frame's state and time (tower targets, facts, the online bench) read it there
            trace["images_at"] = [*trace["kf_end"][:-1], len(trace["t"]) - 1]
        meta = self.task_meta(run.executed)
        nominal = self.scripted_keyframes()
        scenario, seed, variant = self._key
        return Episode(
            episode_id="",
            backend=self.name,
            task=self.scenario_info(scenario)["template"],
            scenario=scenario,
            variant=variant,
            seed=seed,
            pair_id="",
            role="",
            actions=meta.actions,
            horizon=horizon_of(len(nominal)),
            nominal_keyframes=nominal,
            executed_keyframes=list(run.executed),
            camera_names=list(self.camera_names),
            images=run.images,
            state_trace=trace,
            labels=derive_labels(trace, meta),
            task_meta=meta,
            cameras=run.cameras,
        )

    def _picks(self, keyframes: Sequence[Keyframe]) -> set[int] | None:
        """The keyframes an open-loop run renders (None: every one)."""
        if not self.render_frames:
            return None
        return set(sample_keyframes([kf.segment for kf in keyframes], self.render_frames))

    def execute(
        self,
        keyframes: Sequence[Keyframe],
        physics_events: Sequence[PhysicsEvent] = (),
        then: tuple[Sequence[Keyframe], Sequence[PhysicsEvent]] | None = None,
    ) -> Episode:
        """Run keyframes from the state set by the last `reset`, render and label (open loop). With `reuse_prefix`,
        a run from a rebuilt world is recorded for the next run from the same reset (`then`: that run's keyframes
        and events, so that only the state it restarts from is saved), and a run after such a reset starts from
        the recorded run's state where their keyframes part (sim_backends/prefix.py)."""
        render = self._picks(keyframes)
        pre = self._planned(keyframes, physics_events)
        self.begin(physics_events, render)
        run = self._active()
        k = self._fast_forward(pre, run, keyframes, physics_events) if pre is not None else 0
        record = pre is None and self._start_recording(run, keyframes, physics_events, then)
        try:
            for kf in keyframes[k:]:
                self.step(kf)
            if record and then is not None:  # its images before finish() may draw the last keyframe again
                images, cameras = [list(v) for v in run.images], [list(c) for c in run.cameras]
                plan = (list(then[0]), list(then[1]))
                recorded = Prefix(
                    self._key, plan, list(keyframes), render, dict(run.checkpoints or {}), images, cameras
                )
            ep = self.finish()
        except BaseException:
            self._release((run.checkpoints or {}).values())
            raise
        if record:
            self._prefix = recorded
        return ep

    # ---- supervision hooks (closed loop: a supervisor and a correction executor read the episode so far) --
    def executed_so_far(self) -> list[Keyframe]:
        """The keyframes stepped since `begin`, in order (a copy)."""
        return list(self._active().executed)

    def images_so_far(self) -> list[list[bytes]]:
        """PNG bytes of every view at the end of every keyframe stepped so far: `[view][keyframe]` (a copy;
        b"" for a keyframe `begin(render=...)` left out)."""
        return [list(v) for v in self._active().images]

    def _active(self) -> _Run:
        if self._run is None:
            raise RuntimeError("no episode is being recorded: reset() then begin() first")
        return self._run

    def close(self) -> None:  # noqa: B027 - optional hook
        pass

    def __enter__(self) -> "FailureSource":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
