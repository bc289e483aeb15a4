"""Correction strategies (Q6): the paper's correction-strategy table and the rule that picks one.

Each strategy is a fixed instruction with placeholders ({target}, {destination},
{direction}, {action}, {source}, {open_closed}, {open_close}) filled from the task's
metadata, so every instruction stays mappable to robot primitives (the action
dictionary of the supervision issue keys on the strategy id).

Choice rule (the table groups strategies by category, but which one applies depends
on the atomic action that failed):
  - an object fell, or the severity is Fatal            -> MANUAL
  - protocol_violation: S1 (S2-style placement is improper_handling); during stir -> M2
  - improper_handling -> S2;  sequence_reversal -> L1;  step_omission -> L2 with the omitted action
  - pose_control_error / incomplete_trajectory, by action: insert M1, stir M2, open/close of a door M3,
    pour M4, pressing a button P3, place P2, grasp G2, shake G3
  - gripper_control_failure: on a door handle P1, else G1;  object_slippage -> G3
  - target_positioning_deviation -> P2;  operation_position_error: door P1, button P3
  - grasp_target_misalignment -> P4
"""

from __future__ import annotations

import functools
import itertools
import string
from dataclasses import dataclass, replace
from typing import Sequence

from labrobfail_vlm.taxonomy import ATOMIC_ACTIONS, FAILURE_TYPES, Severity

STRATEGIES: dict[str, tuple[str, str]] = {  # id -> (category of the paper's table, instruction)
    "S1": (
        "Safety",
        "Keep the robotic arm position unchanged, maintain gripper state, and keep the arm horizontal "
        "to complete the experiment safely.",
    ),
    "S2": (
        "Safety",
        "After completing the operation, keep the gripper horizontal, move the robotic arm, and place "
        "the {target} steadily.",
    ),
    "L1": (
        "Logic",
        "First move the robotic arm to grasp the {target} with gripper closed, then move to the "
        "{destination} and open the gripper to place.",
    ),
    "L2": (
        "Logic",
        "Pause current execution, return to perform the omitted {action}, then resume the remaining workflow.",
    ),
    "M1": (
        "Motion",
        "Adjust the gripper orientation to horizontal, keep the gripper closed, then move the robotic "
        "arm forward to insert into the {target}.",
    ),
    "M2": (
        "Motion",
        "Keep the gripper closed and orientation unchanged, move the robotic arm side to side "
        "repeatedly until the liquid is fully stirred.",
    ),
    "M3": (
        "Motion",
        "Keep the gripper closed on the door handle and move the robotic arm {direction} until the "
        "door is fully {open_closed}.",
    ),
    "M4": (
        "Motion",
        "Move the robotic arm to align the {source} above the {destination}, keep the gripper closed, "
        "then progressively tilt the gripper until the liquid is fully poured.",
    ),
    "G1": (
        "Grasping",
        "Keep the gripper open and move the robotic arm until the {target} is centered within the "
        "gripper, then close the gripper to secure the grasp.",
    ),
    "G2": (
        "Grasping",
        "Move the robotic arm toward the {target}, adjust the gripper orientation to horizontal, keep "
        "the gripper open until centered, then close the gripper to grasp.",
    ),
    "G3": (
        "Grasping",
        "Keep the gripper closed to secure the {target} and move the robotic arm to the "
        "{destination} while maintaining orientation horizontal.",
    ),
    "P1": (
        "Perception",
        "Move the robotic arm to center the gripper on the door handle, close the gripper to "
        "grasp, then move {direction} to {open_close} the door.",
    ),
    "P2": (
        "Perception",
        "Move the robotic arm to position the {target} above the {destination}, keep the gripper "
        "orientation horizontal, then open the gripper to release.",
    ),
    "P3": (
        "Perception",
        "Move the robotic arm to align the gripper with the {target}, keep the gripper closed, "
        "then move forward until pressed.",
    ),
    "P4": (
        "Perception",
        "Open the gripper to release, reposition the robotic arm to center the {target}, then "
        "close the gripper firmly to secure.",
    ),
    "MANUAL": (
        "Manual Operation",
        "The object has fallen or critical failure occurred, please correct it manually right away.",
    ),
}

_MOTION_BY_ACTION = {"insert": "M1", "stir": "M2", "pour": "M4", "place": "P2", "grasp": "G2", "shake": "G3"}


@dataclass(frozen=True)
class Context:
    """What the rule needs to know about the failure, all derived from simulator metadata."""

    failure_type: str
    action: str  # atomic action of the step where the failure happened
    device: str = ""  # "door" or "button" when the failing step operates one
    fell: bool = False
    fatal: bool = False
    target: str = "object"
    destination: str = "target position"
    source: str = "container"
    omitted: str = "step"
    opening: bool = True  # door steps: opening (else closing)


def choose(ctx: Context) -> str:
    ft, act = ctx.failure_type, ctx.action
    if ctx.fell or ctx.fatal:
        return "MANUAL"
    if ft == "protocol_violation":
        return "M2" if act == "stir" else "S1"
    if ft == "improper_handling":
        return "S2"
    if ft == "sequence_reversal":
        return "L1"
    if ft == "step_omission":
        return "L2"
    if ft in ("pose_control_error", "incomplete_trajectory"):
        if ctx.device == "door":
            return "M3"
        if ctx.device == "button":
            return "P3"
        return _MOTION_BY_ACTION.get(act, "G3")
    if ft == "gripper_control_failure":
        return "P1" if ctx.device == "door" else "G1"
    if ft == "object_slippage":
        return "G3"
    if ft == "target_positioning_deviation":
        return "P2"
    if ft == "operation_position_error":
        return "P3" if ctx.device == "button" else "P1"
    if ft == "grasp_target_misalignment":
        return "P4"
    raise ValueError(f"correction: unknown failure type {ft!r}")


def instruction(strategy: str, ctx: Context) -> str:
    text = STRATEGIES[strategy][1]
    return text.format(
        target=ctx.target,
        destination=ctx.destination,
        source=ctx.source,
        action=ctx.omitted,
        direction="backward" if ctx.opening else "forward",
        open_closed="open" if ctx.opening else "closed",
        open_close="open" if ctx.opening else "close",
    )


def correction(ctx: Context) -> tuple[str, str]:
    """(strategy id, filled instruction) for a failure."""
    sid = choose(ctx)
    return sid, instruction(sid, ctx)


@functools.cache
def strategies_of(category: int) -> frozenset[str]:
    """The strategy ids `choose` can give a failure of the Q5 `category` (1-5): those of its failure types over
    every atomic action and device, plus MANUAL (a fall or a fatal failure, whatever the category). Read off the
    rule itself, so the grouping cannot drift from it."""
    types = [ft.name for ft in FAILURE_TYPES.values() if ft.category == category]
    if not types:
        raise ValueError(f"correction: no failure category {category!r}")
    out = {"MANUAL"}
    for ft, act, dev in itertools.product(types, ATOMIC_ACTIONS, ("", "door", "button")):
        out.add(choose(Context(failure_type=ft, action=act, device=dev)))
    return frozenset(out)


# The severities a fall can carry in the labeler's severity table (sim_backends/labeler.severity): glassware
# off the bench or breaking is Fatal, a vessel lying on its side is tipped over (Risk). `choose` gives MANUAL
# exactly for a fall or a Fatal failure, so Fatal admits only MANUAL and Dangerous or Management incident never
# admit it.
FALL_SEVERITIES = frozenset({Severity.RISK, Severity.FATAL})


def admissible(category: int | None = None, severity: int | None = None) -> frozenset[str]:
    """The strategy ids `choose` can give a failure of the Q5 `category` at the Q4 `severity` (1-4); None for a
    reply not given. Decoding Q6 among these makes the correction agree with the rest of the diagnosis."""
    out = strategies_of(category) if category is not None else frozenset(STRATEGIES)
    if severity == Severity.FATAL:
        return frozenset({"MANUAL"})
    if severity is not None and severity not in FALL_SEVERITIES:
        return out - {"MANUAL"}
    return out


# Places a correction may name besides the scene's objects (failure_context's fallbacks).
GENERIC_DESTINATIONS = ("its original position", "target position")


def candidates(names: Sequence[str], category: int | None = None, severity: int | None = None) -> list[tuple[str, str]]:
    """Every (strategy id, instruction) the template-constrained Q6 decoder may choose, with the placeholders
    filled from `names` (the scene's object and place labels; generic fallbacks are always included).
    `category`, `severity`: the Q5 and Q4 answers, when given: only the strategies they admit (`admissible`), so
    the correction agrees with the diagnosis (a grasping failure is not corrected by redoing an omitted step, a
    recoverable one is not handed to a person)."""
    names = list(dict.fromkeys(n for n in names if n)) or ["object"]
    choices = {
        "target": names,
        "source": names,
        "destination": [*names, *GENERIC_DESTINATIONS],
        "action": list(ATOMIC_ACTIONS),
        "opening": [True, False],
    }
    out: list[tuple[str, str]] = []
    allowed = admissible(category, severity)
    for sid, (_, text) in STRATEGIES.items():
        if sid not in allowed:
            continue
        fields = {f for _, f, _, _ in string.Formatter().parse(text) if f}
        # direction/open_closed/open_close all follow whether a door is being opened
        keys = sorted(
            {
                "opening" if f in ("direction", "open_closed", "open_close") else "omitted" if f == "action" else f
                for f in fields
            }
        )
        pools = [choices["action" if k == "omitted" else k] for k in keys]
        for combo in itertools.product(*pools):
            filled = dict(zip(keys, combo))
            if "destination" in filled and filled["destination"] in (filled.get("target"), filled.get("source")):
                continue  # one object both moved and where it goes ("the beaker above the beaker") reads wrong
            ctx = replace(Context(failure_type="", action=""), **filled)
            out.append((sid, instruction(sid, ctx)))
    return list(dict.fromkeys(out))
