"""The supervisor interface, its registry, and the prefix grid of the keyframes so far.

A supervisor is asked, between steps of a running episode, whether a failure has shown up; its
`Verdict` carries the diagnosis and the correction's primitives (labrobfail_vlm/actions.py), which the
loop hands to the executor (sim_backends/executor.py). After a correction the loop calls `handled`, and
the supervisor reports only failures that show up later.
"""

from __future__ import annotations

import io
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from PIL import Image

from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.grid import GridConfig, build_grid, sample_keyframes, whole_grid_picks
from labrobfail_vlm.registry import Registry
from sim_backends.policies.base import EpisodeContext
from sim_backends.source import FailureSource

SUPERVISORS = Registry(
    "supervisor",
    lazy={
        "none": "sim_backends.supervision.oracle",
        "oracle": "sim_backends.supervision.oracle",
        "vlm": "sim_backends.supervision.vlm",
    },
)
register_supervisor, make_supervisor = SUPERVISORS.register, SUPERVISORS.make  # lazy: imported on first use


@dataclass
class Verdict:
    failure: bool
    failure_type: str | None = None
    failure_keyframe: int | None = None  # index into the executed keyframes
    correction: str = ""
    strategy: str | None = None
    primitives: list[dict[str, Any]] = field(default_factory=list)
    diagnosis: dict[str, Any] = field(default_factory=dict)  # the supervisor's full answer (Diagnosis, evidence)
    grid: Image.Image | None = None  # what the supervisor looked at (VLM)

    def to_log(self) -> dict[str, Any]:
        return {
            "failure": self.failure,
            "failure_type": self.failure_type,
            "failure_keyframe": self.failure_keyframe,
            "correction": self.correction,
            "strategy": self.strategy,
            "primitives": self.primitives,
            "diagnosis": self.diagnosis,
        }


class Supervisor(ABC):
    name = "abstract"

    def reset(self, ctx: EpisodeContext) -> None:
        self.ctx = ctx
        self.handled_upto = -1  # failures at or before this executed keyframe were corrected already

    def check_cameras(self, rendered: list[str]) -> None:  # noqa: B027 - optional hook
        """Called before the first trial with the views the backend renders: refuse (ConfigError) a view it needs."""

    def check_drawing(self, options: dict[str, Any]) -> None:  # noqa: B027 - optional hook
        """Called before the first trial with the backend's own options: refuse (ConfigError) a run that draws its
        grids otherwise than the supervisor learned from (labrobfail_vlm/drawing.py)."""

    @abstractmethod
    def query(self, src: FailureSource, final: bool = False) -> Verdict:
        """Has a (new) failure shown up in the episode so far? `final`: the policy has stopped."""

    def handled(self, src: FailureSource, acted: bool = True) -> None:
        """A correction ran: what has happened up to now is dealt with. `acted`: whether it moved anything (a plan
        refused before its first primitive did not; the report is dealt with all the same)."""
        self.handled_upto = len(src.executed_so_far()) - 1


# ---- the live prefix grid ----------------------------------------------------------------------------------
@dataclass
class LiveGrid:
    image: Image.Image
    keyframes: list[int]  # executed keyframe index shown in each visible cell (grid frame i+1 -> keyframes[i])
    visible: int


def view_indices(rendered: list[str], views: list[str] | None) -> list[int] | None:
    """Where the named views lie among the backend's rendered views (None: every rendered view). A policy may
    need a view the supervisor's model was never shown (ACT's wrist camera): the grid keeps to its own views."""
    if views is None:
        return None
    missing = [v for v in views if v not in rendered]
    if missing or not views:
        raise ConfigError(f"vlm.views: the backend renders {rendered}, not {missing or views}")
    return [rendered.index(v) for v in views]


def live_picks(done: list, nominal: list, max_frames: int, final: bool = False) -> tuple[list[int], list[int]]:
    """live_grid's cells: the executed keyframes that count as one each (`units`, indices into `done`) and the
    grid's picks, indices into the units and the plan's remaining keyframes after them (a pick >= len(units) is a
    cell not reached yet). Its rules are live_grid's."""
    if final:  # the episode is whole: the dataset's rule (no cells for the plan's remaining keyframes)
        units = whole_grid_picks([k.name for k in done], [k.segment for k in done], max_frames)
        return units, list(range(len(units)))
    units = [i for i in range(len(done)) if i == len(done) - 1 or done[i + 1].name != done[i].name]
    names = [k.name for k in nominal]
    last = done[units[-1]].name if units else None
    rest = nominal[len(names) - names[::-1].index(last) :] if last in names else nominal[len(units) :]
    return units, sample_keyframes([done[i].segment for i in units] + [k.segment for k in rest], max_frames)


def live_grid(
    src: FailureSource, nominal: list, cfg: GridConfig, final: bool = False, views: list[int] | None = None
) -> LiveGrid:
    """The prefix grid of an episode so far, laid out as the dataset lays out prefix grids.

    Consecutive executed keyframes with one name (a learned policy's control ticks, a correction's
    keyframes) count as one keyframe, shown by its last image. The cells are sampled from the keyframes so
    far plus the plan's remaining ones (the episode's length is not known yet), and the cells not reached
    yet stay blank, as in a training prefix grid (`build_grid(..., visible=k)`).

    `final`: the policy has stopped, so the episode is whole and laid out as the dataset lays out a whole
    trajectory (`whole_grid_picks`): no cells are kept for plan steps it never ran, and a policy's rollout written
    as a shard (labrobfail-supervise shards=true) trains on this very grid.

    `views`: the rendered views shown, in order (`view_indices`); None: all of them.
    """
    units, picks = live_picks(src.executed_so_far(), nominal, cfg.max_frames, final)
    shown = [p for p in picks if p < len(units)]
    pngs = src.images_so_far()
    pngs = pngs if views is None else [pngs[i] for i in views]
    blank = np.zeros((8, 8, 3), np.uint8)
    frames = [
        [Image.open(io.BytesIO(view[units[p]])).convert("RGB") if p < len(units) else blank for p in picks]
        for view in pngs
    ]
    return LiveGrid(build_grid(frames, cfg, visible=len(shown)), [units[p] for p in shown], len(shown))
