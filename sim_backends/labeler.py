"""Labels derived from a recorded state trace, never from the injected perturbation.

Inputs are the episode's state trace (columns sampled at the trace's own
`rate_hz`) and task metadata (`TaskMeta` or its JSON dict: the nominal plan, its
steps and goals, object geometry; schema in sim_backends/schema.py). The controller's
program counter (which step the arm executes) is part of the recorded state,
as in a real robot log. Decision, in order:

1. success = every task goal holds on the settled final state and no glassware broke (`broken`: an impact at
   >= BREAK_SPEED is the Fatal severity's breakage, whether or not the piece ended where its goal wanted it);
2. otherwise each detector scans the trace for its state signature and
   reports the sample where it first shows; the earliest wins (ties broken by
   the order below), giving the failure type and its onset: the first failure keyframe (the keyframe that
   sample falls in) and the sample's sim time (`Labels.onset_s`); a winning liquid failure is dated from its
   pour's alignment when that went astray (`poured_astray`);
3. severity from the trace and final state (the rule table in `severity` and docs/ARCHITECTURE.md).

A failure no detector explains gets no type (`Labels.explained` is False): it is never given a
default type; the generator leaves it out of the dataset and counts it in the manifest.

Thresholds are module constants so that tests and docs can quote them.
"""

from __future__ import annotations

from typing import Any, Callable, Optional, Union

import numpy as np

from labrobfail_vlm.taxonomy import Severity, category_of
from sim_backends.goals import OFF_BENCH, UPRIGHT_TILT, failed_goals, rod_in_vessel, stir_samples, tilt
from sim_backends.schema import MOVABLE, TaskMeta, Trace, meta_dict, samples_in
from sim_backends.types import Labels, quat_to_matrix, rotation_angle

Meta = dict[str, Any]  # TaskMeta.to_dict(): what a shard stores, so labels re-derive from a shard alone
Event = tuple[int, str, str]  # (sample index, failure type, evidence)

MISALIGN_XY = 0.012  # m: gripper-to-object lateral offset at closure that counts as a misaligned grasp
OPEN_WIDTH = 0.07  # m: finger opening that means the gripper did not close
EMPTY_GRIP = 0.5  # closed fingers under this fraction of a vessel's planned grasp width hold nothing
SLIP_DRIFT = 0.04  # m: object-to-gripper drift while held, measured in the gripper frame
POSE_ERR = 0.3  # rad: end-effector orientation error against the plan
WRONG_PLACE = 0.08  # m: release this far from the planned spot = put somewhere else entirely
STILL = 0.005  # m: end-effector displacement between keyframes that counts as not moving
INSERT_MISS = 0.015  # m: a rod/tube this far from its hole or vessel axis at the end of an insertion
HANDLE_MISS = 0.015  # m: gripper-to-handle/button offset that misses it
RELEASE_LEAD = 0.2  # s: slip checks stop this long before the release keyframe ends (the fingers open)
# liquid particles newly outside every vessel that make a spill, where too little reached the destination (a pour
# that delivers enough may lose more: 323 of the 497 successful pours of outputs/r14 did)
SPILL_PARTICLES = 5
GRAVITY = 9.81  # m/s^2
BREAK_SPEED = 1.2  # m/s: glassware that hits something this fast (a fall of ~8 cm or more) counts as broken


def _kf_samples(trace: Trace, meta: Meta, names: set[str]) -> list[int]:
    """End-of-keyframe sample indices of the executed keyframes with these names."""
    return [trace["kf_end"][i] for i, n in enumerate(meta["executed"]) if n in names and i < len(trace["kf_end"])]


def _nominal(meta: Meta, name: str) -> dict:
    return next(k for k in meta["nominal"] if k["name"] == name)


def _executed_steps(trace: Trace, meta: Meta) -> list[int]:
    """Step (segment) order the controller actually ran, from the program counter column."""
    seg = {k["name"]: k["segment"] for k in meta["nominal"]}
    order: list[int] = []
    for kf in trace["kf"]:
        s = seg[meta["executed"][kf]] if kf < len(meta["executed"]) else None
        if s is not None and (not order or order[-1] != s):
            order.append(s)
    return order


def detect_logic(trace: Trace, meta: Meta) -> Optional[Event]:
    """Compare the step order the controller ran with the plan's: a step never run is an omission,
    a step run early is a reversal. The failure shows at the first keyframe of the out-of-place step."""
    nominal_order = [s["index"] for s in meta["steps"]]
    ran = _executed_steps(trace, meta)
    if ran == nominal_order:
        return None
    seg = {k["name"]: k["segment"] for k in meta["nominal"]}
    p = next((i for i, (a, b) in enumerate(zip(ran, nominal_order)) if a != b), len(ran))
    if p >= len(ran):  # the run is a prefix of the plan: its last steps never ran
        missing = nominal_order[p:]
        return trace["kf_end"][-1], "step_omission", f"steps {missing} never ran"
    s, expected = ran[p], nominal_order[p]
    kind = "step_omission" if expected not in ran else "sequence_reversal"
    i = next(i for i, n in enumerate(meta["executed"]) if seg[n] == s)
    j = trace["kf_end"][i - 1] + 1 if i > 0 else 0
    return (
        j,
        kind,
        (
            f"step {s} ({meta['steps'][s]['action']}) ran where step {expected} "
            f"({meta['steps'][expected]['action']}) was due; steps ran in order {ran}"
        ),
    )


def detect_grasp(trace: Trace, meta: Meta) -> Optional[Event]:
    for st in meta["steps"]:
        if st["action"] != "grasp" or meta["objects"][st["object"]]["kind"] not in MOVABLE:
            continue
        js = _kf_samples(trace, meta, {st["close_kf"]})
        if not js:
            continue
        j, obj = js[0], st["object"]
        # A vessel keeps closed fingers about its diameter apart; fingers that closed far past it (a vessel
        # pushed aside by an off-centre reach, touching a fingertip) hold nothing. A rod is too thin to tell.
        empty = meta["objects"][obj]["kind"] == "vessel" and trace["width"][j] < EMPTY_GRIP * st.get("width", 0.0)
        if trace[f"{obj}.contacts"][j] > 0 and not empty:
            continue
        grasp_pt = np.asarray(trace[f"{obj}.pos"][j]) + np.asarray(st["grip_offset"])
        off = float(np.linalg.norm(np.asarray(trace["ee_pos"][j])[:2] - grasp_pt[:2]))
        if empty and off > MISALIGN_XY:
            return j, "grasp_target_misalignment", f"fingers closed on nothing {off:.3f} m beside {obj}"
        if empty:
            continue  # closed on nothing right at the vessel: no detector here explains it
        if trace["width"][j] >= OPEN_WIDTH:
            return (
                j,
                "gripper_control_failure",
                f"fingers stayed open (width {trace['width'][j]:.3f} m) at {st['close_kf']}",
            )
        if off > MISALIGN_XY:
            return j, "grasp_target_misalignment", f"fingers closed {off:.3f} m beside {obj} with no contact"
        return j, "gripper_control_failure", f"fingers closed on {obj} without contact (offset {off:.3f} m)"
    return None


def _in_gripper(trace: Trace, obj: str, j: int) -> np.ndarray:
    """Object position in the end-effector frame (a pour rotates the gripper; that is no slip)."""
    r = quat_to_matrix(tuple(trace["ee_quat"][j]))
    return r.T @ (np.asarray(trace[f"{obj}.pos"][j]) - np.asarray(trace["ee_pos"][j]))


def detect_slip(trace: Trace, meta: Meta) -> Optional[Event]:
    for st in meta["steps"]:
        if st["action"] != "grasp" or "close_kf" not in st:
            continue
        obj = st["object"]
        js = _kf_samples(trace, meta, {st["close_kf"]})
        if not js or trace[f"{obj}.contacts"][js[0]] == 0:
            continue
        j0 = js[0]
        rel = [k for s in meta["steps"] if s.get("object") == obj and "release_kf" in s for k in [s["release_kf"]]]
        ends = [e for e in _kf_samples(trace, meta, set(rel)) if e > j0]
        if not ends and not any(s.get("object") == obj for s in meta["steps"][st["index"] + 1 :]):
            j1 = len(trace["t"])  # the task ends holding it (a pick): watch it to the end
        else:
            # The release keyframe (or, without one, the last: an insertion pushes the rod in the fingers)
            # opens the fingers: stop before it starts (by the program counter) and RELEASE_LEAD before
            # its end, whichever is earlier.
            j1 = min(ends, default=len(trace["t"]) - 1)
            rel_i = trace["kf"][j1]
            start = next((k for k in range(j0, j1 + 1) if trace["kf"][k] == rel_i), j1)
            j1 = max(j0, min(start, j1 - 1 - samples_in(trace, RELEASE_LEAD)))
        d0 = _in_gripper(trace, obj, j0)
        for j in range(j0, j1):
            d = _in_gripper(trace, obj, j)
            if float(np.linalg.norm(d - d0)) > SLIP_DRIFT:
                # Fingers commanded open before the release keyframe: the object was let go, not lost.
                opened = next((k for k in range(j0, j + 1) if trace["grip_cmd"][k] == 0), None)
                if opened is not None:
                    how = (
                        f"the fingers stayed open at {st['close_kf']} and left {obj} behind"
                        if opened == j0
                        else f"the gripper opened while carrying {obj}, before its release"
                    )
                    return opened, "gripper_control_failure", how
                return j, "object_slippage", f"{obj} drifted {np.linalg.norm(d - d0):.3f} m from the gripper while held"
    return None


def _stopped_after(trace: Trace, meta: Meta, st: dict, j: int) -> bool:
    """The end effector covered less than half of the step's planned motion after sample j."""
    plan = {k["name"]: np.asarray(k["pos"]) for k in meta["nominal"]}
    names = [n for n in st["keyframes"] if n in plan]
    planned = max(float(np.linalg.norm(plan[n] - plan[st["contact_kf"]])) for n in names)
    ends = [e for e in _kf_samples(trace, meta, set(names)) if e >= j]
    moved = max(
        (float(np.linalg.norm(np.asarray(trace["ee_pos"][e]) - np.asarray(trace["ee_pos"][j]))) for e in ends),
        default=0.0,
    )
    return planned > 0.05 and moved < 0.5 * planned


def detect_operation(trace: Trace, meta: Meta) -> Optional[Event]:
    """Door and button steps: the articulation did not move because the gripper missed its handle/button."""
    for st in meta["steps"]:
        obj = st.get("object")
        if obj is None or f"{obj}.q" not in trace or "contact_point" not in st:
            continue
        js = _kf_samples(trace, meta, {st["contact_kf"]})
        if not js:
            continue
        j = js[0]
        if _stopped_after(trace, meta, st, j):
            continue  # the arm stopped mid-step: the incomplete-trajectory detector decides
        i = trace["kf_end"].index(j)
        # The contact keyframe holds still by design (close on the handle); compare with the approach start.
        k0 = trace["kf_end"][max(0, i - 2)]
        if i > 0 and float(np.linalg.norm(np.asarray(trace["ee_pos"][j]) - np.asarray(trace["ee_pos"][k0]))) < STILL:
            continue  # the arm never moved in to make contact: an incomplete trajectory, not a miss
        q = trace[f"{obj}.q"]
        moved = max(abs(v - q[j]) for v in q[j:]) if meta["objects"][obj]["kind"] == "oven" else max(q[j:])
        needed = 0.5 if meta["objects"][obj]["kind"] == "oven" else 0.006
        if moved >= needed:
            continue  # the door or button moved: this operation worked
        if meta["objects"][obj]["kind"] == "oven" and trace["width"][j] >= OPEN_WIDTH:
            return j, "gripper_control_failure", f"fingers stayed open on the {obj}'s handle"
        off = float(np.linalg.norm(np.asarray(trace["ee_pos"][j]) - np.asarray(st["contact_point"])))
        if off > HANDLE_MISS:
            return j, "operation_position_error", f"gripper {off:.3f} m off the {obj}'s handle/button; it did not move"
    return None


def detect_incomplete(trace: Trace, meta: Meta) -> Optional[Event]:
    """The arm stood still over the last keyframes although the plan still had motion left."""
    ends = trace["kf_end"]
    ee = [np.asarray(trace["ee_pos"][j]) for j in ends]
    plan = [np.asarray(_nominal(meta, n)["pos"]) for n in meta["executed"]]
    k = len(ee) - 1
    while k > 0 and float(np.linalg.norm(ee[k] - ee[k - 1])) < STILL:
        k -= 1
    left = sum(float(np.linalg.norm(plan[i + 1] - plan[i])) for i in range(k, len(plan) - 1))
    if k >= len(ee) - 1 or left < 0.03:
        return None
    return (
        ends[k] + 1,
        "incomplete_trajectory",
        f"arm stood still from keyframe {k + 1} on with {left:.3f} m of planned motion left",
    )


def detect_place(trace: Trace, meta: Meta) -> Optional[Event]:
    for st in meta["steps"]:
        if st["action"] != "place":
            continue
        names = set(st["keyframes"])
        ids = [i for i, n in enumerate(meta["executed"]) if n in names]
        if not ids:
            continue
        obj = st["object"]
        for i in ids:
            j = trace["kf_end"][i]
            twist = rotation_angle(trace["ee_quat"][j], _nominal(meta, meta["executed"][i])["quat"])
            if twist > POSE_ERR:
                return (
                    j,
                    "pose_control_error",
                    f"gripper twisted {twist:.2f} rad off the plan while placing {obj}",
                )
        j = _kf_samples(trace, meta, {st["release_kf"]})
        if not j:
            continue
        j = j[0]
        if trace[f"{obj}.contacts"][j] > 0 and trace["grip_cmd"][j] == 1:
            # the gripper was still commanded shut and holds the object when the release ends (the recorded
            # command, as a robot log has it; the width cannot tell a wide vessel from open fingers)
            return j, "gripper_control_failure", f"the gripper stayed closed on {obj} through its release"
        fin = np.asarray(trace[f"{obj}.pos"][-1])
        dest = np.asarray(st["dest_xy"])
        miss = float(np.linalg.norm(fin[:2] - dest))
        if miss <= 0.04:
            continue
        ee_off = float(
            np.linalg.norm(np.asarray(trace["ee_pos"][j]) - np.asarray(_nominal(meta, st["release_kf"])["pos"]))
        )
        if st.get("returning") and ee_off > WRONG_PLACE:
            return j, "improper_handling", f"{obj} was set down {miss:.3f} m from its home instead of being returned"
        return j, "target_positioning_deviation", f"{obj} released {miss:.3f} m from the target"
    return None


def detect_insert(trace: Trace, meta: Meta) -> Optional[Event]:
    """A tube lowered beside its rack hole: at the end of the insertion it is off the hole. (A rod that misses
    the vessel it should stir is the stirring detector's protocol violation.)"""
    for st in meta["steps"]:
        if st["action"] != "insert" or "dest_xy" not in st or st.get("dest") in meta["objects"]:
            continue
        ends = _kf_samples(trace, meta, set(st["keyframes"][-1:]))
        if not ends:
            continue
        j, obj = ends[0], st["object"]
        off = float(np.linalg.norm(np.asarray(trace[f"{obj}.pos"][j])[:2] - np.asarray(st["dest_xy"])))
        if off > INSERT_MISS:
            return j, "target_positioning_deviation", f"{obj} went in {off:.3f} m beside its target {st['dest']}"
    return None


def pour_alignment(
    trace: Trace, meta: Meta, source: str, into: str, before: Optional[int] = None
) -> Optional[tuple[int, float]]:
    """Where a pour from `source` into `into` went astray before any liquid moved: the end of the pour's first
    keyframe (the hand brought beside the destination to pour, before the tilt) and how far the hand then stood from
    its planned place relative to the destination (m), when that is more than the destination's radius: the mouth,
    once tilted, no longer comes over the opening. None for a pour aligned as planned or never aligned. A pour run
    again (after a correction) is judged by its own alignment: the latest one before sample `before` (None: any).

    A liquid failure that wins the detectors' race is dated from here rather than from the first drop astray
    (`poured_astray`): the positioning (or the wrong vessel) is in the recorded state when the alignment ends, and a
    grid's frame of that keyframe shows the vessel held beside its target, about three seconds before the liquid
    leaves (the 7 Dec recipe's train and val splits: 409 successful pours 0.002-0.004 m; 50 of 53 spills and all 12
    pours into another vessel 0.06-0.25 m). The threshold is the opening's own size, not fitted to those figures."""
    st = next((s for s in meta["steps"] if s["action"] == "pour" and s["object"] == source and s["dest"] == into), None)
    ends = _kf_samples(trace, meta, {st["keyframes"][0]}) if st else []
    # the latest alignment before `before`: a pour run again after a correction is judged by its own alignment
    ends = [j for j in ends if before is None or j < before]
    if not ends:
        return None
    j = ends[-1]
    planned = np.asarray(_nominal(meta, st["keyframes"][0])["pos"][:2]) - np.asarray(meta["objects"][into]["home"][:2])
    held = np.asarray(trace["ee_pos"][j][:2]) - np.asarray(trace[f"{into}.pos"][j][:2])
    miss = float(np.linalg.norm(held - planned))
    return (j, miss) if miss > float(meta["objects"][into]["dims"]["radius"]) else None


def poured_astray(trace: Trace, meta: Meta, j: int, why: str) -> tuple[int, str]:
    """The onset of a liquid failure (a spill, or liquid into another vessel) first found at sample j: the end of its
    pour's alignment when that alignment went astray (pour_alignment, the latest before j), else j. derive_labels
    applies it to the winning event only, after the detectors raced on their own samples, so a redated failure never
    takes the place of another detector's earlier one (no type changes) and the live supervisor (oracle.py), which
    runs the detectors themselves, still sees the liquid when it leaves."""
    for g in [g for g in meta["goals"] if g["kind"] == "liquid"]:
        off = pour_alignment(trace, meta, g["source"], g["into"], before=j)
        if off is not None:
            return off[0], f"{g['source']} was aligned {off[1]:.3f} m off its pour over {g['into']}, then {why}"
    return j, why


def detect_liquid(trace: Trace, meta: Meta) -> Optional[Event]:
    goals = [g for g in meta["goals"] if g["kind"] == "liquid"]
    for g in goals:
        for col in [c for c in trace if c.startswith("liquid.")]:
            v = col.split(".", 1)[1]
            if v in (g["into"], g["source"], "outside"):
                continue
            base = trace[col][0]
            for j, n in enumerate(trace[col]):
                if n >= base + 2:
                    return j, "protocol_violation", f"liquid from {g['source']} entered {v}, not {g['into']}"
    return None


def spilled(trace: Trace, j: int = -1) -> int:
    """Liquid particles outside every vessel at sample j, beyond those outside at the start."""
    col = trace.get("liquid.outside")
    return int(col[j] - col[0]) if col else 0


def detect_spill(trace: Trace, meta: Meta) -> Optional[Event]:
    """Liquid ended up outside every vessel (poured beside the target, or flung out) and too little of it
    reached the destination. A pour that delivers enough despite a few drops outside did not fail there."""
    col = trace.get("liquid.outside")
    goals = [g for g in meta["goals"] if g["kind"] == "liquid"]
    if not col or not goals or not any(g in failed_goals(trace, meta) for g in goals):
        return None
    j = next((j for j in range(len(col)) if col[j] - col[0] >= SPILL_PARTICLES), None)
    if j is None:
        return None
    return j, "target_positioning_deviation", f"{spilled(trace)} liquid particles landed outside every vessel (spill)"


def detect_stir(trace: Trace, meta: Meta) -> Optional[Event]:
    goal = next((g for g in meta["goals"] if g["kind"] == "stirred"), None)
    js = stir_samples(trace, meta)
    if goal is None or not js:
        return None
    if sum(rod_in_vessel(trace, meta, goal["object"], goal["vessel"], j) for j in js) >= goal["min_fraction"] * len(js):
        return None
    return js[0], "protocol_violation", "the rod was not inside the vessel while stirring (insufficient stirring)"


# Order breaks ties between detectors firing at the same sample (causes before effects).
DETECTORS: list[Callable[[Trace, Meta], Optional[Event]]] = [
    detect_logic,
    detect_grasp,
    detect_operation,
    detect_slip,
    detect_place,
    detect_insert,
    detect_liquid,
    detect_spill,
    detect_stir,
    detect_incomplete,
]


def impact_speed(trace: Trace, obj: str) -> float:
    """Fastest downward speed of an object at a trace sample (m/s).

    A sample interval's mean speed lags a falling object's speed at the interval's end by g*dt/2 (0.12 m/s at
    40 Hz), so the mean alone read a 12 cm fall as 1.1-1.3 m/s depending on where the impact fell between two
    samples. The end-of-interval speed of a free fall is the mean plus g*dt/2; an interval that ends in an impact
    never reads above the true impact speed."""
    z = [p[2] for p in trace[f"{obj}.pos"]]
    rate = float(trace.get("rate_hz", 40.0))
    means = [(z[j - 1] - z[j]) * rate for j in range(1, len(z))]
    return max((m + GRAVITY / (2 * rate) for m in means if m > 0), default=0.0)


HELD = 0.1  # m: a vessel this close to the hand is in it (a pour tilts its vessel on purpose)
# s: a vessel tipped past UPRIGHT_TILT out of the hand has fallen over only if it stays tipped this long (or until the
# trace ends). A retreating open hand that catches a beaker's rim rocks it to 0.65 rad and it rights itself in 0.2 s.
TIPPED_FOR = 0.5
# m from the arm's base, horizontally: the Panda's reach at grasp height for the hand's approach along +x.
# Measured with PyBullet's IK on the Panda model (straight ahead and 0.5 rad aside): the hand reaches a side grasp
# 3-8 cm above the bench within 1.5 cm out to 0.90 m and misses by 3-8 cm from 0.925 to 0.975 m (a top-down grasp
# already misses by 1.3 cm at 0.80 m).
REACH = 0.90


def _beyond_reach(pos, base) -> bool:
    return float(np.hypot(pos[0] - base[0], pos[1] - base[1])) > REACH


def _tipped_from(quats: list, j: int, n: int) -> bool:
    """Tipped past UPRIGHT_TILT at sample j and at each of the n samples after it that the trace has."""
    return all(tilt(q) > UPRIGHT_TILT for q in quats[j : j + n + 1])


def irreversible_sample(trace: Trace, meta: Meta) -> Optional[tuple[int, str]]:
    """The first sample of an event no correction undoes, and which: liquid spilled outside every vessel where too
    little reached its destination ("spill", as detect_spill reads it: a pour that delivers enough loses some drops),
    a movable object knocked off the bench or a vessel tipped over out of the hand for TIPPED_FOR ("fall"), glassware
    moving down fast enough to break (>= BREAK_SPEED, read as `impact_speed` reads it: "breakage"), a movable object
    that began within the arm's reach pushed beyond it out of the hand (> REACH from the arm's base: "out_of_reach";
    never read when the meta has no `robot_base`). None when none happens. An alarm raised before this sample could
    still have saved the run; the online bench counts those."""
    meta = meta_dict(meta)
    movables = [k for k, o in meta["objects"].items() if o["kind"] in MOVABLE]
    vessels = {m for m in movables if meta["objects"][m]["kind"] == "vessel"}
    rate = float(trace.get("rate_hz", 40.0))
    low = meta["bench_top"] + OFF_BENCH
    bad = failed_goals(trace, meta)
    lost = any(g["kind"] == "liquid" and g in bad for g in meta["goals"])
    liquid = trace.get("liquid.outside") if lost else None
    base = meta.get("robot_base")
    reachable = {m for m in movables if base is not None and not _beyond_reach(trace[f"{m}.pos"][0], base)}
    stay = samples_in(trace, TIPPED_FOR)
    for j in range(len(trace["t"])):
        if liquid and liquid[j] - liquid[0] >= SPILL_PARTICLES:
            return j, "spill"
        for m in movables:
            pos = trace[f"{m}.pos"]
            if pos[j][2] < low:
                return j, "fall"
            if (
                j
                and pos[j - 1][2] > pos[j][2]
                and (pos[j - 1][2] - pos[j][2]) * rate + GRAVITY / (2 * rate) >= BREAK_SPEED
            ):
                return j, "breakage"
            far = np.linalg.norm(np.subtract(pos[j], trace["ee_pos"][j])) > HELD
            if m in vessels and far and _tipped_from(trace[f"{m}.quat"], j, stay):
                return j, "fall"
            if m in reachable and far and _beyond_reach(pos[j], base):
                return j, "out_of_reach"
    return None


def broken(trace: Trace, meta: Meta) -> list[str]:
    """The task's movable objects whose trace holds a breaking impact (`impact_speed` >= BREAK_SPEED)."""
    return [k for k, o in meta["objects"].items() if o["kind"] in MOVABLE and impact_speed(trace, k) >= BREAK_SPEED]


def severity(trace: Trace, meta: Meta, failure_type: str) -> Severity:
    """The severity rule table (first match wins; docs/ARCHITECTURE.md quotes it):

    Fatal: glassware knocked off the bench, or falling fast enough to break (>= BREAK_SPEED).
    Risk: glassware tipped over or slipping, or liquid spilled outside every vessel.
    Management incident: an oven door left open, equipment not returned.
    Dangerous: anything else (the task cannot proceed without someone stepping in)."""
    movables = [k for k, o in meta["objects"].items() if o["kind"] in MOVABLE]
    if any(trace[f"{m}.pos"][-1][2] < meta["bench_top"] + OFF_BENCH for m in movables) or broken(trace, meta):
        return Severity.FATAL
    vessels = [m for m in movables if meta["objects"][m]["kind"] == "vessel"]
    if (
        any(tilt(trace[f"{m}.quat"][-1]) > UPRIGHT_TILT for m in vessels)
        or spilled(trace) >= SPILL_PARTICLES
        or failure_type == "object_slippage"
    ):
        return Severity.RISK
    ovens = [k for k, o in meta["objects"].items() if o["kind"] == "oven"]
    if failure_type == "improper_handling" or any(trace[f"{o}.q"][-1] > 0.3 for o in ovens):
        return Severity.MANAGEMENT_INCIDENT
    return Severity.DANGEROUS


def derive_labels(trace: Trace, meta: Union[TaskMeta, Meta]) -> Labels:
    meta = meta_dict(meta)
    bad = failed_goals(trace, meta)
    # A breaking drop onto a goal that still holds (a beaker released 10 cm up that lands upright on its mark) is
    # no success: the same impact is Fatal everywhere else, and a grid drawing broken glass shows shards.
    shattered = broken(trace, meta)
    if not bad and not shattered:
        return Labels(success=True, evidence="all goals hold")
    events = [(e, rank) for rank, d in enumerate(DETECTORS) if (e := d(trace, meta)) is not None]
    failed = ", ".join([g["kind"] for g in bad] + [f"{m} broken" for m in shattered])
    if not events:  # never guessed: the episode is left out of the dataset and counted
        return Labels(success=False, evidence=f"unexplained: no detector fired; failed goals: {failed}")
    (j, ftype, why), rank = min(events, key=lambda er: (er[0][0], er[1]))
    if DETECTORS[rank] in (detect_liquid, detect_spill):
        j, why = poured_astray(trace, meta, j, why)
    kf = next((i for i, e in enumerate(trace["kf_end"]) if e >= j), len(trace["kf_end"]) - 1)
    return Labels(
        success=False,
        failure_type=ftype,
        category=int(category_of(ftype)),
        severity=int(severity(trace, meta, ftype)),
        failure_keyframe=kf,
        evidence=f"{why}; failed goals: {failed}",
        onset_s=round(float(trace["t"][j]) - float(trace["t"][0]), 4),
    )
