"""The `none` supervisor (never intervenes) and the `oracle`: the labeler on the live state trace.

The oracle is the upper bound of supervision: it reads the simulator state, which no camera-based
supervisor sees. It runs the labeler's detectors (sim_backends/labeler.py) on the trace recorded so far;
the step-order check is made prefix-aware here (on a running episode the steps not run yet are not
omitted). The correction is the one the dataset would annotate for that failure (labrobfail_data/annotate.py's
`failure_context` + the strategy table), mapped through the action dictionary.
"""

from __future__ import annotations

from typing import Any

from labrobfail_vlm.actions import to_primitives
from labrobfail_vlm.corrections import correction
from labrobfail_vlm.taxonomy import category_of
from sim_backends import labeler
from sim_backends.failure_context import failure_context
from sim_backends.goals import failed_goals
from sim_backends.schema import TaskMeta, Trace
from sim_backends.source import FailureSource
from sim_backends.supervision.base import Supervisor, Verdict, register_supervisor

Event = tuple[int, str, str]


@register_supervisor("none")
class NoSupervisor(Supervisor):
    name = "none"

    def query(self, src: FailureSource, final: bool = False) -> Verdict:
        return Verdict(False)


def logic_so_far(trace: Trace, meta: TaskMeta) -> Event | None:
    """Step order of a running episode against the plan's order up to the same length."""
    seg = meta.executed_steps()
    ran: list[int] = []
    for k in trace["kf"]:
        if k < len(seg) and (not ran or ran[-1] != seg[k]):
            ran.append(seg[k])
    plan = [s.index for s in meta.steps]
    p = next((i for i, (a, b) in enumerate(zip(ran, plan)) if a != b), None)
    if p is None:
        return None
    s, expected = ran[p], plan[p]
    first = seg.index(s)
    j = trace["kf_end"][first - 1] + 1 if first > 0 else 0
    kind = "step_omission" if expected not in ran else "sequence_reversal"
    return (
        j,
        kind,
        f"step {s} ({meta.steps[s].action}) ran where step {expected} ({meta.steps[expected].action}) was due",
    )


def live_failure(trace: Trace, meta: TaskMeta, after_sample: int) -> Event | None:
    """The earliest failure signature after sample `after_sample` (ties: the labeler's detector order)."""
    md = meta.to_dict()
    events = []
    for rank, det in enumerate(labeler.DETECTORS):
        e = logic_so_far(trace, meta) if det is labeler.detect_logic else det(trace, md)
        if e is not None and e[0] > after_sample:
            events.append((e, rank))
    return min(events, key=lambda er: (er[0][0], er[1]))[0] if events else None


def unmet_goal(trace: Trace, meta: TaskMeta, goals: list[dict[str, Any]] | None) -> Event | None:
    """Once the policy has stopped, a goal that still fails with no detector signature. The dataset leaves such
    an episode out (its labeler never guesses a type); a supervisor must still act, and what it knows is exactly
    this: the policy stopped before the task was done. That is an incomplete trajectory, whose correction (the
    strategy table, by the step's action) resumes the unfinished step."""
    md = meta.to_dict()
    bad = failed_goals(trace, {**md, "goals": goals} if goals is not None else md)
    if not bad:
        return None
    return len(trace["t"]) - 1, "incomplete_trajectory", f"policy stopped with goal {bad[0]['kind']!r} unmet"


@register_supervisor("oracle")
class OracleSupervisor(Supervisor):
    name = "oracle"

    def reset(self, ctx: Any) -> None:
        super().reset(ctx)
        self.after_sample = 0

    def query(self, src: FailureSource, final: bool = False) -> Verdict:
        trace = src.trace_so_far()
        meta = src.task_meta(src.executed_so_far())
        if final:
            # The policy has stopped, so the goals decide: every goal holds = nothing to correct, whatever a detector
            # saw on the way (a placement made with a twisted wrist that still stands on the target); correcting it
            # could only undo it (glass broken on the way fails the episode by the labeler's rule, but no correction
            # mends it). Otherwise the earliest signature names the failure; a failed goal with no signature is an
            # incomplete trajectory.
            unmet = unmet_goal(trace, meta, self.ctx.goals)
            ev = None if unmet is None else live_failure(trace, meta, self.after_sample) or unmet
        else:
            ev = live_failure(trace, meta, self.after_sample)
        if ev is None:
            return Verdict(False)
        j, ftype, why = ev
        kf = next((i for i, e in enumerate(trace["kf_end"]) if e >= j), len(trace["kf_end"]) - 1)
        md = meta.to_dict()
        sev = int(labeler.severity(trace, md, ftype))
        ctx = failure_context({"failure_keyframe": kf, "failure_type": ftype, "severity": sev}, md, trace)
        sid, text = correction(ctx)
        return Verdict(
            True,
            ftype,
            kf,
            text,
            sid,
            to_primitives(text, list(meta.labels.values())),
            {"evidence": why, "severity": sev, "category": int(category_of(ftype)), "sample": j},
        )

    def handled(self, src: FailureSource, acted: bool = True) -> None:
        super().handled(src, acted)
        self.after_sample = len(src.trace_so_far()["t"]) - 1
