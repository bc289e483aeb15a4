"""A policy's own rollouts as shards: `labrobfail-supervise shards=true` writes every trial's episode, labeled by
the labeler from the simulator state like a generated one, in the generator's shard format.

Why: a supervisor trained only on the scripted policy's injected failures meets other failures at a learned
policy's stops (the pour ACT stops with nothing poured, and the model names a grasp-and-place; docs/EXPERIMENTS.md,
2 Dec). Its rollouts, built with `labrobfail-build-dataset` and added to a training run (`labrobfail-train
extra_train=[...]`), show the model those failures on the very grid it is shown when the policy stops
(`labrobfail_vlm.grid.whole_grid_picks`, one rule for both).

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
from sim_backends.shards import episode_row, manifest, write_shard
from sim_backends.supervision.loop import TaskFamily
from sim_backends.types import Episode


def check_family(family: TaskFamily) -> None:
    if family.steps is not None or family.goals is not None:
        raise ConfigError(
            f"shards: task {family.name!r} judges success by goals of its own; its episodes' labels would not "
            "say what its trials were judged on (write rollouts of a family without steps or goals)"
        )


class RolloutShards:
    """Buffers trials' episodes and writes them `per_shard` at a time under `out_dir` (shard-00000.parquet, ...)."""

    def __init__(self, out_dir: Path, frames: int, policy: str, per_shard: int = 20):
        self.dir, self.frames, self.policy, self.per_shard = Path(out_dir), frames, policy, per_shard
        self.dir.mkdir(parents=True, exist_ok=True)
        self.rows: list[dict] = []
        self.buffer: list[dict] = []
        self.shards = self.unexplained = 0

    def add(self, ep: Episode, family: str, supervisor: str) -> None:
        if not ep.labels.success and ep.labels.failure_type is None:
            self.unexplained += 1
            return
        ep.pair_id = f"{self.policy}-{family}-s{ep.seed}"
        ep.episode_id = f"{ep.pair_id}-{supervisor}"
        ep.role = "rollout"
        kfs = ep.executed_keyframes
        keep = set(whole_grid_picks([k.name for k in kfs], [k.segment for k in kfs], self.frames))
        ep.images = [[png if i in keep else b"" for i, png in enumerate(view)] for view in ep.images]
        row = episode_row(ep)
        self.buffer.append(row)
        self.rows.append({k: v for k, v in row.items() if k not in ("images", "state_trace")})
        if len(self.buffer) >= self.per_shard:
            self.flush()

    def flush(self) -> None:
        if self.buffer:
            write_shard(self.dir / f"shard-{self.shards:05d}.parquet", self.buffer)
            self.shards, self.buffer = self.shards + 1, []

    def close(self) -> None:
        self.flush()
        run = {"source": "rollouts", "policy": self.policy, "render_frames": self.frames}
        run["unexplained"] = self.unexplained
        atomic_write_json(self.dir / "run.json", run)
        atomic_write_json(self.dir / "manifest.json", manifest(self.rows, run))
