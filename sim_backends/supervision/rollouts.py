"""A policy's own rollouts as shards: `labrobfail-supervise shards=true` writes every trial's episode, labeled by
the labeler from the simulator state like a generated one, in the generator's shard format.

Why: a supervisor trained only on the scripted policy's injected failures meets other failures at a learned
policy's stops (the pour ACT stops with nothing poured, and the model names a grasp-and-place; docs/EXPERIMENTS.md,
2 Dec). Its rollouts, built with `labrobfail-build-dataset` and added to a training run (`labrobfail-train
extra_train=[...]`), show the model those failures on the very grid it is shown when the policy stops
(`labrobfail_vlm.grid.whole_grid_picks`, one rule for both; with `broken_glass`, a piece that breaks in the
settling redraws the last frame, as in generated shards).

Only the images of the keyframes a `frames`-frame grid shows are kept (a 400-tick rollout renders 400 per view), and
run.json says so (`render_frames`), so the dataset builder refuses another grid size. Both runs of one seed (with and
without the supervisor) share a `pair_id`, hence a split. A family that runs part of a plan or judges success by goals
of its own (`steps`, `goals`) is refused: its episodes' labels judge the scenario's goals. A failure no detector
explains is left out and counted (run.json `unexplained`), as the generator leaves such a pair out: no label is guessed.
"""

from __future__ import annotations

from pathlib import Path

from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.grid import whole_grid_picks
from labrobfail_vlm.io import atomic_write_json
from sim_backends.shards import episode_row, manifest, read_labels, write_shard
from sim_backends.supervision.loop import TaskFamily
from sim_backends.types import Episode, Labels


def check_family(family: TaskFamily) -> None:
    if family.steps is not None or family.goals is not None:
        raise ConfigError(
            f"shards: task {family.name!r} judges success by goals of its own; its episodes' labels would not "
            "say what its trials were judged on (write rollouts of a family without steps or goals)"
        )


class RolloutShards:
    """One supervisor's trials' episodes under `out_dir`, each written as its trial ends (shard-<task>-<trial>.parquet),
    so that a trial the run log records as finished has its shard (sim_backends/supervision/resume.py)."""

    def __init__(self, out_dir: Path, frames: int, policy: str, supervisor: str, backend_kwargs: dict | None = None):
        self.dir, self.frames, self.policy, self.supervisor = Path(out_dir), frames, policy, supervisor
        self.backend_kwargs = dict(backend_kwargs or {})  # in run.json: what the grids drew (labrobfail_vlm/drawing.py)
        self.dir.mkdir(parents=True, exist_ok=True)

    def add(self, ep: Episode, family: str, trial: int) -> None:
        if not ep.labels.explained:  # no label is guessed: left out, counted at close
            return
        ep.pair_id = f"{self.policy}-{family}-s{ep.seed}"
        ep.episode_id = f"{ep.pair_id}-{self.supervisor}"
        ep.role = "rollout"
        kfs = ep.executed_keyframes
        keep = set(whole_grid_picks([k.name for k in kfs], [k.segment for k in kfs], self.frames))
        ep.images = [[png if i in keep else b"" for i, png in enumerate(view)] for view in ep.images]
        write_shard(self.dir / f"shard-{family}-{trial:05d}.parquet", [episode_row(ep)])

    def close(self, trials: list[dict]) -> None:
        """run.json and manifest.json over every shard in the folder; `trials`: the run log's episode records of
        this supervisor's trials (this run's and a resumed run's earlier ones), whose unexplained failures it counts."""
        run = {"source": "rollouts", "policy": self.policy, "render_frames": self.frames}
        run["backend_kwargs"] = self.backend_kwargs
        labels = [Labels(t["labels"]["success"], t["labels"]["failure_type"]) for t in trials]
        run["unexplained"] = sum(not x.explained for x in labels)
        atomic_write_json(self.dir / "run.json", run)
        atomic_write_json(self.dir / "manifest.json", manifest(read_labels(self.dir.glob("shard-*.parquet")), run))
