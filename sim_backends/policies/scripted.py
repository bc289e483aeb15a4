"""The scripted policy: the task's keyframes with a failure injected by the existing operators.

The controlled baseline of the supervision experiments. The perturbation is drawn as
`failure_generator.run_injected` draws it for the same seed (its random stream and weights, so its failing
episodes are the dataset's), restricted to the specs that touch the steps the task family runs (e.g. "pick":
the grasp only); a trial is perturbed with probability `inject_prob`.

After a correction that ran in full (`resume: replan`, the default) the policy re-plans: it goes on with the
nominal plan after the plan keyframe nearest to where the correction left the arm, so an intervention clears
the injected control or semantic fault (a physics change persists: it is in the world). Note that this also
restarts a stalled (truncated) controller whatever the correction said. `resume: queue` keeps its own
remaining keyframes instead (a stalled controller stays stalled and undoes the correction): the stricter
measure of what the corrections themselves achieve.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sim_backends.failure_generator import apply_spec, draw_spec, perturbation_rng
from sim_backends.perturbations.physics import PhysicsEvent
from sim_backends.policies.base import Action, EpisodeContext, Policy, register_policy
from sim_backends.source import Observation


def resume_index(plan: list, state: dict[str, Any], step: int | None = None) -> int:
    """Where a plan goes on after a correction: the keyframe after the one nearest to the arm (position, plus
    5 cm for a different gripper command). Of near ties, one in `step` (the plan step the correction redid, e.g.
    the grasp a regrasp made again: a pour sets the vessel down where it grasped it, and only the step tells a
    fresh grasp from the set-back), else the later one (a grasp's reach and close coincide)."""
    ee, grip = np.asarray(state["ee_pos"], float), int(state["grip_cmd"])
    cost = [float(np.linalg.norm(np.asarray(k.pos) - ee)) + 0.05 * (k.gripper != grip) for k in plan]
    best = min(cost)
    ties = [j for j, c in enumerate(cost) if c <= best + 0.005]
    return max([j for j in ties if plan[j].segment == step] or ties) + 1


def spec_applies(spec: dict[str, Any], names: set[str], steps: int) -> bool:
    """Whether a perturbation spec acts on the given keyframes / first `steps` steps."""
    if spec.get("level") == "physics":
        return any(a in names for a in spec.get("at", []))
    if spec.get("level") == "control":
        return any(k in names for k in spec.get("keyframes", []))
    idx = spec.get("steps", [spec.get("step")])  # omitting or swapping steps needs two of them to run
    return steps > 1 and all(i is not None and int(i) < steps for i in idx)


@register_policy("scripted")
class ScriptedPolicy(Policy):
    name = "scripted"

    def __init__(self, inject_prob: float = 1.0, resume: str = "replan"):
        if not 0.0 <= float(inject_prob) <= 1.0:
            raise ValueError(f"scripted.inject_prob: must be in [0, 1], got {inject_prob!r}")
        if resume not in ("replan", "queue"):
            raise ValueError(f"scripted.resume: expected replan or queue, got {resume!r}")
        self.inject_prob, self.resume = float(inject_prob), resume
        self.nominal: list = []
        self.queue: list = []
        self.i = 0
        self.perturbation: dict[str, Any] = {"level": "none"}

    def reset(self, ctx: EpisodeContext) -> list[PhysicsEvent]:
        kfs, events = list(ctx.nominal), []
        self.nominal = list(ctx.nominal)
        self.perturbation = {"level": "none"}
        steps = 1 + max((k.segment for k in kfs), default=-1)
        specs = [s for s in ctx.perturbations if spec_applies(s, {k.name for k in kfs}, steps)]
        inject = np.random.default_rng([ctx.seed, 0x1AB]).random() < self.inject_prob
        if specs and inject:
            rng = perturbation_rng(ctx.seed)  # the generator's stream for this seed, weights included
            kfs, events, self.perturbation = apply_spec(draw_spec(specs, rng), kfs, ctx.positions, rng)
        self.queue, self.i = kfs, 0
        return events

    def act(self, obs: Observation) -> Action | None:
        if self.i >= len(self.queue):
            return None
        self.i += 1
        return Action.from_keyframe(self.queue[self.i - 1])

    def after_correction(self, obs: Observation, executed: bool = True, step: int | None = None) -> None:
        if self.resume == "queue" or not self.nominal or not executed:  # a refused correction changes nothing
            return
        self.queue, self.i = self.nominal[resume_index(self.nominal, obs.state, step) :], 0

    def info(self) -> dict[str, Any]:
        return {"perturbation": self.perturbation}
