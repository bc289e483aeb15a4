"""The supervised loop: a policy acts, a supervisor watches, corrections run, everything is logged.

    for each step:  obs = src.observe(); action = policy.act(obs); src.step(keyframe of the action)
                    at each keyframe boundary (or every `query_every` steps): verdict = supervisor.query(src)
                    failure and budget left -> CorrectionExecutor(src).run(verdict.primitives),
                                               supervisor.handled(src), policy.after_correction(obs)
                    (a plan the executor refused before it moved anything is neither an intervention nor a
                    reason for the policy to re-plan)
    policy stops:   one more query (a failure that shows only once the policy stops); a correction that runs
                    there hands control back to the policy (corrections end "then resume the remaining
                    workflow"), which is reviewed again when it stops; then src.finish()

Every query is a JSONL record (latency, diagnosis, primitives, the executor's outcome, the grid's path);
every trial ends with an `episode` record, whose `outcome` is success, failure or policy_error (the policy
could not act: a bad reply from a policy server, a dead server; `error` holds its one-line reason: the trial
ends there, the run goes on). Success is judged by the task family's goals on the settled
final state, with nothing broken (`TaskFamily`: "pick" is the grasp step of a pick-and-place scenario, judged by
"held").
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, TextIO

import numpy as np

from labrobfail_vlm.grid import GridConfig
from sim_backends.executor import CorrectionExecutor
from sim_backends.goals import failed_goals
from sim_backends.labeler import broken
from sim_backends.policies.base import Action, EpisodeContext, Policy, PolicyError
from sim_backends.source import FailureSource, Observation
from sim_backends.supervision.base import Supervisor, live_grid
from sim_backends.types import Episode, Keyframe, rotation_angle

REACH_POS, REACH_ROT = 0.02, 0.25  # m, rad: a target this close to a plan keyframe is that keyframe


@dataclass
class LoopConfig:
    query_every: int = 0  # 0: at each keyframe boundary; k > 0: every k policy steps; -1: never during the
    # episode, only the final query (a post-hoc review of the whole trajectory, the grid a model was trained on)
    budget: int = 2  # corrections per episode
    on_manual: str = "stop"  # a manual correction hands over to a person: "stop" the episode or "continue"
    max_steps: int = 600  # policy steps per episode
    final_query: bool = True
    grids: str = "failures"  # save the grid of "all" queries, of "failures" only, or "none"

    def __post_init__(self) -> None:
        if self.on_manual not in ("stop", "continue"):
            raise ValueError(f"loop.on_manual: expected stop or continue, got {self.on_manual!r}")
        if self.grids not in ("all", "failures", "none"):
            raise ValueError(f"loop.grids: expected all, failures or none, got {self.grids!r}")
        if self.budget < 0 or self.query_every < -1 or self.max_steps < 1:
            raise ValueError("loop: budget must be >= 0, query_every >= -1, max_steps >= 1")
        if self.query_every == -1 and not self.final_query:
            raise ValueError("loop.query_every=-1 asks only the final query; it needs loop.final_query=true")


@dataclass
class TaskFamily:
    """A row of the paper's recovery table: scenarios, how much of their plan runs, what counts as success."""

    name: str
    scenarios: list[str]
    steps: int | None = None  # run only the plan's first `steps` steps (pick = the grasp of pick-and-place)
    goals: list[dict[str, Any]] | None = None  # replace the scenario's goals (pick: the object is held)

    def plan(self, nominal: list[Keyframe]) -> list[Keyframe]:
        return [k for k in nominal if self.steps is None or k.segment < self.steps]

    def success(self, ep: Episode) -> bool:
        if self.goals is None:
            return bool(ep.labels.success)
        meta = {**ep.task_meta.to_dict(), "goals": self.goals}
        return not failed_goals(ep.state_trace, meta) and not broken(ep.state_trace, meta)  # the labeler's rule


def _matches(pos: Any, quat: Any, grip: int, k: Keyframe) -> bool:
    return (
        float(np.linalg.norm(np.asarray(pos) - np.asarray(k.pos))) < REACH_POS
        and rotation_angle(tuple(quat), k.quat) < REACH_ROT
        and int(grip) == k.gripper
    )


class PhaseTracker:
    """Names the steps of a policy that does not know the plan (ACT, OpenVLA) after the plan keyframe they
    head for, so the labeler's program counter and the grid follow the task's progress. A target that
    matches one of the next three plan keyframes (2 cm, 0.25 rad, same gripper command) takes its name and
    moves the progress there; one that matches the current keyframe keeps it (holding, settling); any other
    target is on its way to the next keyframe. A gripper change gets settling time, as the plan's grasp and
    release keyframes have."""

    def __init__(self, nominal: list[Keyframe]):
        self.nominal = nominal
        self.c = -1  # the plan keyframe commanded last

    def keyframe(self, a: Action, state: dict[str, Any] | None = None) -> Keyframe:
        settle = int(a.settle)
        named = [i for i, k in enumerate(self.nominal) if k.name == a.name] if a.name is not None else []
        if named:
            i = named[0]
        else:
            ahead = range(self.c + 1, min(self.c + 4, len(self.nominal)))
            i = next((q for q in ahead if _matches(a.pos, a.quat, a.gripper, self.nominal[q])), -1)
            if i < 0:
                i = (
                    self.c
                    if self.c >= 0 and _matches(a.pos, a.quat, a.gripper, self.nominal[self.c])
                    else min(self.c + 1, len(self.nominal) - 1)
                )
            if state is not None and not settle and int(a.gripper) != int(state["grip_cmd"]):
                settle = 50 if a.gripper else 40
        if named or _matches(a.pos, a.quat, a.gripper, self.nominal[i]):
            self.c = max(self.c, i)
        base = self.nominal[i]
        return Keyframe(
            base.name,
            tuple(map(float, a.pos)),
            tuple(map(float, a.quat)),
            int(a.gripper),
            base.target,
            base.segment,
            base.action,
            float(a.speed),
            settle,
        )


class RunLog:
    """JSONL records, one line each, flushed as they come (a killed run keeps what it logged), and grids. Appends:
    a resumed run's log goes on from the earlier run's (sim_backends/supervision/resume.py cut it first)."""

    def __init__(self, out_dir: str | Path, name: str = "log.jsonl"):
        self.dir = Path(out_dir)
        (self.dir / "grids").mkdir(parents=True, exist_ok=True)
        self.f: TextIO = open(self.dir / name, "a", encoding="utf-8")

    def write(self, rec: dict[str, Any]) -> None:
        self.f.write(json.dumps(rec, default=str) + "\n")
        self.f.flush()

    def grid(self, img: Any, stem: str) -> str:
        import io

        from labrobfail_vlm.io import atomic_write_bytes

        buf = io.BytesIO()
        img.save(buf, format="PNG")
        rel = f"grids/{stem}.png"
        atomic_write_bytes(self.dir / rel, buf.getvalue())
        return rel

    def close(self) -> None:
        self.f.close()


def episode_context(src: FailureSource, family: TaskFamily, scenario: str, seed: int, variant: str) -> EpisodeContext:
    meta = src.task_meta([])
    return EpisodeContext(
        src.name,
        scenario,
        seed,
        variant,
        meta.description,
        family.plan(src.scripted_keyframes()),
        src.object_positions(),
        list(src.scenario_info(scenario)["perturbations"]),
        sorted(set(meta.labels.values())),
        list(src.camera_names),
        family.goals,
    )


@dataclass
class _Trial:
    queries: int = 0
    interventions: int = 0
    latency: list[float] = field(default_factory=list)
    stopped: str | None = None
    error: str | None = None  # the policy's one-line reason when it could not act (PolicyError): the trial ends
    steps: int = 0  # policy steps
    corrected: bool = False  # the last query's correction ran


def _act(
    src: FailureSource,
    policy: Policy,
    supervisor: Supervisor,
    executor: CorrectionExecutor,
    tracker: PhaseTracker,
    cfg: LoopConfig,
    log: RunLog | None,
    trial: str,
    t: _Trial,
    grid_cfg: GridConfig,
    ctx: EpisodeContext,
) -> None:
    """Step the policy, querying as `cfg` says, until it stops, errs, a correction stops the episode or the
    step limit is reached."""
    prev_name: str | None = None
    while t.steps < cfg.max_steps:
        obs = src.observe()
        try:
            a = policy.act(obs)
        except PolicyError as e:  # a bad reply, a dead server: this trial ends, the run goes on
            t.error = " ".join(str(e).split()) or type(e).__name__  # one line, whatever the message held
            t.stopped = f"policy error: {t.error}"
            return
        if a is None:
            return
        kf = tracker.keyframe(a, obs.state)
        src.step(kf)
        t.steps += 1
        obs = src.observe()
        if cfg.query_every < 0:
            due = False
        elif cfg.query_every:
            due = t.steps % cfg.query_every == 0
        else:  # a keyframe boundary: a named (plan) step ran, or the plan keyframe an unnamed policy's ticks are
            # named after changed. Not before the tracker has seen one reached: the first tick of ACT is named after
            # the keyframe it heads for, and a query there would show a one-cell grid of a move just begun
            due = a.name is not None or (kf.name != prev_name and tracker.c >= 0)
        prev_name = kf.name
        if due and not _query(src, policy, supervisor, executor, cfg, log, trial, t, obs, grid_cfg, ctx):
            return


def run_trial(
    src: FailureSource,
    policy: Policy,
    supervisor: Supervisor,
    family: TaskFamily,
    scenario: str,
    seed: int,
    variant: str,
    cfg: LoopConfig,
    log: RunLog | None,
    trial: str,
    grid_cfg: GridConfig = GridConfig(),
    keep: Callable[[Episode], None] | None = None,
) -> dict[str, Any]:
    """One trial; `keep` receives its finished episode (labeled from the simulator state: RolloutShards)."""
    src.reset(scenario, seed, variant)
    ctx = episode_context(src, family, scenario, seed, variant)
    events = policy.reset(ctx)
    supervisor.reset(ctx)
    src.begin(events)
    tracker, t = PhaseTracker(ctx.nominal), _Trial()
    executor = CorrectionExecutor(src)
    while True:
        _act(src, policy, supervisor, executor, tracker, cfg, log, trial, t, grid_cfg, ctx)
        if not src.executed_so_far():  # nothing ran (a policy that failed at once): hold still, so the episode
            # has a keyframe to label
            s = src.observe().state
            src.step(
                tracker.keyframe(
                    Action(tuple(s["ee_pos"]), tuple(s["ee_quat"]), int(s["grip_cmd"]), name=tracker.nominal[0].name)
                )
            )
        if not cfg.final_query or t.stopped is not None:
            break
        _query(src, policy, supervisor, executor, cfg, log, trial, t, src.observe(), grid_cfg, ctx, final=True)
        if not t.corrected or t.stopped is not None or t.steps >= cfg.max_steps:
            break
        # A correction ran once the policy had stopped. Many end "... then resume the remaining workflow" and the
        # policy has re-planned from the corrected state (`after_correction`): it goes on, and is reviewed again
        # when it stops (the budget bounds the rounds).
    ep = src.finish()
    success = family.success(ep)
    if keep is not None:
        keep(ep)
    # `success` is judged on the final state whatever happened; `outcome` also says why a trial ended early
    outcome = "policy_error" if t.error is not None else ("success" if success else "failure")
    res = {
        "event": "episode",
        "trial": trial,
        "scenario": scenario,
        "seed": seed,
        "variant": variant,
        "family": family.name,
        "policy": policy.name,
        "supervisor": supervisor.name,
        "outcome": outcome,
        "error": t.error,
        "success": success,
        "steps": t.steps,
        "keyframes": len(ep.executed_keyframes),
        "queries": t.queries,
        "interventions": t.interventions,
        "stopped": t.stopped,
        "labels": ep.labels.to_dict(),
        "latency_s": t.latency,
        **policy.info(),
    }
    if log is not None:
        log.write(res)
    return res


def _query(
    src: FailureSource,
    policy: Policy,
    sup: Supervisor,
    executor: CorrectionExecutor,
    cfg: LoopConfig,
    log: RunLog | None,
    trial: str,
    t: _Trial,
    obs: Observation,
    grid_cfg: GridConfig,
    ctx: EpisodeContext,
    final: bool = False,
) -> bool:
    """Ask the supervisor once and correct on a failure; False when the episode must stop."""
    t0 = time.perf_counter()
    v = sup.query(src, final)
    t.latency.append(round(time.perf_counter() - t0, 4))
    t.queries += 1
    rec: dict[str, Any] = {
        "event": "query",
        "trial": trial,
        "keyframe": obs.keyframe,
        "final": final,
        "latency_s": t.latency[-1],
        **v.to_log(),
    }
    if log is not None and (cfg.grids == "all" or (cfg.grids == "failures" and v.failure)):
        img = v.grid if v.grid is not None else live_grid(src, ctx.nominal, grid_cfg, final).image
        rec["grid"] = log.grid(img, f"{trial}-q{t.queries:03d}")
    go_on, t.corrected = True, False
    if v.failure and t.interventions >= cfg.budget:
        rec["outcome"] = {"executed": False, "error": "intervention budget spent"}
    elif v.failure:
        res = executor.run(v.primitives, final)
        # a plan refused before its first primitive (an impossible return, an unknown primitive) left the world as
        # it was: it is no intervention (the budget counts corrections that acted) and the policy's plan or action
        # chunks still hold, so it is not told to re-plan. A hand-over to a person counts.
        moved = res.keyframes > 0
        sup.handled(src, moved or bool(res.manual))  # the report is dealt with, even when its plan was refused
        rec["outcome"] = res.to_dict()
        if moved or res.manual:
            t.interventions += 1
            policy.after_correction(src.observe(), res.executed, res.step)
        t.corrected = res.executed and moved
        if res.manual and cfg.on_manual == "stop":
            t.stopped, go_on = "manual correction", False
    if log is not None:
        log.write(rec)
    return go_on
