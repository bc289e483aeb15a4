"""Labeler detectors on small synthetic traces: one case per failure type (11) plus successes.

The traces come from a few lines of kinematics instead of a simulator: the end effector moves
linearly to each executed keyframe, an object is held when the fingers close on its grasp point,
and each case bends exactly the signal its detector reads. Real-episode checks are in
tests/test_pybullet_episodes.py; these pin every state signature down without physics.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from labrobfail_vlm.taxonomy import FAILURE_TYPE_NAMES, category_of
from sim_backends.labeler import derive_labels
from sim_backends.schema import Goal, NominalKeyframe, ObjectInfo, Step, TaskMeta, check_trace

Q0 = (0.0, 0.0, 0.0, 1.0)
HOME, TARGET = (0.5, 0.0, 0.0), (0.5, 0.25, 0.0)
GRIP = (0.0, 0.0, 0.05)  # end effector above the object's base when it holds it
PER_KF = 10  # samples per keyframe
RATE = 40.0


def _twist(angle: float) -> tuple[float, ...]:
    """A rotation of `angle` rad about x, as an (x, y, z, w) quaternion."""
    return (math.sin(angle / 2), 0.0, 0.0, math.cos(angle / 2))


def _pick_place_plan(dest=TARGET, returning=False) -> list[tuple[str, tuple, int]]:
    x, y, z = HOME
    dx, dy, _ = dest
    return [
        ("s0_pre", (x - 0.1, y, 0.05), 0),
        ("s0_reach", (x, y, 0.05), 0),
        ("s0_close", (x, y, 0.05), 1),
        ("s0_lift", (x, y, 0.17), 1),
        ("s1_carry", (dx, dy, 0.17), 1),
        ("s1_lower", (dx, dy, 0.05), 1),
        ("s1_release", (dx, dy, 0.05), 0),
        ("s1_retreat", (dx - 0.1, dy, 0.05), 0),
    ]


def _pick_place_meta(executed: list[str], returning: bool = False) -> TaskMeta:
    dest = HOME if returning else TARGET
    plan = _pick_place_plan(dest)
    steps = [
        Step(
            0,
            "grasp",
            object="obj",
            keyframes=[n for n, *_ in plan[:4]],
            close_kf="s0_close",
            grip_offset=list(GRIP),
            width=0.054,
        ),
        Step(
            1,
            "place",
            object="obj",
            dest="obj" if returning else "target",
            dest_xy=list(dest[:2]),
            returning=returning,
            keyframes=[n for n, *_ in plan[4:]],
            release_kf="s1_release",
        ),
    ]
    goals = [
        Goal("at", {"object": "obj", "xy": "obj" if returning else "target", "tol": 0.04}),
        Goal("upright", {"object": "obj"}),
        Goal("released", {"object": "obj"}),
    ]
    return TaskMeta(
        steps=steps,
        goals=goals,
        objects={"obj": ObjectInfo("vessel", {"radius": 0.025, "height": 0.09, "neck": 0.0}, list(HOME))},
        places={"obj": list(HOME), "target": list(TARGET)},
        nominal=[NominalKeyframe(n, list(p), list(Q0), g, int(n[1])) for n, p, g in plan],
        executed=executed,
        bench_top=0.0,
        liquid_total={},
        labels={"obj": "beaker"},
        description="test",
    )


def _simulate(
    meta: TaskMeta,
    shift: dict[str, tuple] | None = None,
    twist: dict[str, float] | None = None,
    stuck_open: bool = False,
    drop_during: str | None = None,
    freeze_after: str | None = None,
    spill_into: str | None = None,
) -> dict[str, Any]:
    """A pick-and-place trace of meta.executed at 40 Hz; the keyword arguments bend one signal each."""
    plan = {k.name: (np.asarray(k.pos), k.gripper) for k in meta.nominal}
    shift, twist = shift or {}, twist or {}
    tr: dict[str, Any] = {
        c: [] for c in ("t", "kf", "ee_pos", "ee_quat", "width", "grip_cmd", "obj.pos", "obj.quat", "obj.contacts")
    }
    if spill_into:
        tr.update({"liquid.obj": [], "liquid.dest": [], f"liquid.{spill_into}": [], "liquid.outside": []})
    ee, quat, obj, held = np.array([0.4, 0.0, 0.3]), Q0, np.asarray(HOME, float), False
    frozen: tuple | None = None

    def sample(i: int, g: int, spill: int) -> None:
        tr["t"].append(round(len(tr["t"]) / RATE, 4))
        tr["kf"].append(i)
        tr["ee_pos"].append([round(float(v), 4) for v in ee])
        tr["ee_quat"].append(list(quat))
        tr["width"].append(0.08 if (stuck_open or not g) else 0.054 if held else 0.0)
        tr["grip_cmd"].append(g)
        tr["obj.pos"].append([round(float(v), 4) for v in obj])
        tr["obj.quat"].append(list(quat) if held else list(obj_quat))
        tr["obj.contacts"].append(2 if held else 0)
        if spill_into:
            tr["liquid.obj"].append(10 - spill)
            tr["liquid.dest"].append(0)
            tr[f"liquid.{spill_into}"].append(spill)
            tr["liquid.outside"].append(0)

    obj_quat, spill = Q0, 0
    sample(0, 0, 0)
    tr["kf_end"] = []
    for i, name in enumerate(meta.executed):
        goal, g = plan[name]
        goal = goal + np.asarray(shift.get(name, (0, 0, 0)))
        if frozen is not None:
            goal, g = frozen
        start, q = ee.copy(), _twist(twist[name]) if name in twist else Q0
        for s in range(1, PER_KF + 1):
            ee = start + (goal - start) * s / PER_KF
            quat = q
            if held and name == drop_during and s == PER_KF // 2:  # the object slips out mid-move
                held, obj = False, np.array([obj[0], obj[1], 0.0])
            # The fingers close on the grasp point by the end of a closing keyframe.
            if s == PER_KF and g and not held and not stuck_open and np.linalg.norm(ee - obj - GRIP) < 0.012:
                held = True
            if held:
                obj = ee - np.asarray(GRIP)
            if spill_into and name == "s1_carry":
                spill = min(3, spill + 1)
            sample(i, g, spill)
        if not g and held:
            held, obj, obj_quat = False, np.array([obj[0], obj[1], 0.0]), quat
        tr["kf_end"].append(len(tr["t"]) - 1)
        if name == freeze_after:
            frozen = (ee.copy(), g)
    tr["rate_hz"] = RATE
    return tr


def _button_case(miss: float) -> tuple[dict[str, Any], TaskMeta]:
    x, y, top = 0.5, 0.1, 0.05
    plan = [
        ("s0_above", (x, y, top + 0.08)),
        ("s0_touch", (x, y, top + 0.015)),
        ("s0_press", (x, y, top - 0.004)),
        ("s0_release", (x, y, top + 0.08)),
    ]
    meta = TaskMeta(
        steps=[
            Step(
                0,
                "close",
                object="button",
                keyframes=[n for n, _ in plan],
                contact_kf="s0_press",
                contact_point=[x, y, top - 0.004],
            )
        ],
        goals=[Goal("button", {"object": "button", "min_travel": 0.007})],
        objects={"button": ObjectInfo("button", {"travel": 0.012, "top": top}, [x, y, 0.0])},
        places={"button": [x, y, 0.0]},
        nominal=[NominalKeyframe(n, list(p), list(Q0), 1, 0) for n, p in plan],
        executed=[n for n, _ in plan],
        bench_top=0.0,
        liquid_total={},
        labels={},
        description="press",
    )
    tr: dict[str, Any] = {c: [] for c in ("t", "kf", "ee_pos", "ee_quat", "width", "grip_cmd", "button.q")}
    tr["kf_end"], ee = [], np.array([0.4, 0.0, 0.3])
    for i, (name, pos) in enumerate(plan):
        goal, start = np.asarray(pos) + (np.array([miss, 0, 0]) if name in ("s0_touch", "s0_press") else 0), ee
        for s in range(1, PER_KF + 1):
            ee = start + (goal - start) * s / PER_KF
            pressed = np.linalg.norm(ee[:2] - [x, y]) < 0.01 and ee[2] < top
            for c, v in (
                ("t", len(tr["t"]) / RATE),
                ("kf", i),
                ("ee_pos", [float(v) for v in ee]),
                ("ee_quat", list(Q0)),
                ("width", 0.0),
                ("grip_cmd", 1),
                ("button.q", 0.01 if pressed else 0.0),
            ):
                tr[c].append(v)
        tr["kf_end"].append(len(tr["t"]) - 1)
    tr["rate_hz"] = RATE
    return tr, meta


NOMINAL = [n for n, *_ in _pick_place_plan()]
S0, S1 = NOMINAL[:4], NOMINAL[4:]


def _case(kind: str) -> tuple[dict[str, Any], TaskMeta]:
    if kind == "operation_position_error":
        return _button_case(miss=0.03)
    if kind == "button_success":
        return _button_case(miss=0.0)
    executed = {"step_omission": S1, "sequence_reversal": S1 + S0}.get(kind, NOMINAL)
    meta = _pick_place_meta(list(executed), returning=kind == "improper_handling")
    if kind == "protocol_violation":  # the held vessel's liquid lands in a bystander vessel
        meta.goals.append(Goal("liquid", {"into": "dest", "min_fraction": 0.5, "source": "obj"}))
        meta.liquid_total = {"obj": 10}
    bend: dict[str, Any] = {
        "gripper_control_failure": {"stuck_open": True},
        "grasp_target_misalignment": {"shift": {"s0_reach": (0, 0.03, 0), "s0_close": (0, 0.03, 0)}},
        "object_slippage": {"drop_during": "s1_carry"},
        "pose_control_error": {"twist": {"s1_lower": 0.5, "s1_release": 0.5}},
        "improper_handling": {"shift": {n: (0, 0.15, 0) for n in S1[1:]}},
        "target_positioning_deviation": {"shift": {n: (0, 0.06, 0) for n in S1[1:]}},
        "protocol_violation": {"spill_into": "bystander"},
        "incomplete_trajectory": {"freeze_after": "s0_lift"},
    }.get(kind, {})
    return _simulate(meta, **bend), meta


@pytest.mark.parametrize("kind", ["success", "button_success"])
def test_success_when_every_goal_holds(kind):
    tr, meta = _case(kind)
    assert check_trace(tr, meta) == []
    lab = derive_labels(tr, meta)
    assert lab.success and lab.failure_type is None, lab.evidence


@pytest.mark.parametrize("kind", FAILURE_TYPE_NAMES)
def test_each_failure_type_has_its_detector(kind):
    tr, meta = _case(kind)
    assert check_trace(tr, meta) == []
    lab = derive_labels(tr, meta)
    assert not lab.success and lab.failure_type == kind, lab.evidence
    assert lab.category == int(category_of(kind)) and 0 <= lab.failure_keyframe < len(meta.executed)
    assert derive_labels(tr, meta.to_dict()) == lab  # the JSON form a shard stores labels the same


def test_slip_window_follows_the_trace_rate():
    """The 0.2 s release lead is converted with rate_hz: at 4x the rate the window spans 4x the samples."""
    from sim_backends.schema import samples_in

    assert samples_in({"rate_hz": 40.0}, 0.2) == 8 and samples_in({"rate_hz": 160.0}, 0.2) == 32
    assert samples_in({}, 0.2) == 8  # traces from before the rate was recorded were 40 Hz


def test_keyframe_of_a_failure_is_where_it_shows():
    tr, meta = _case("grasp_target_misalignment")
    assert derive_labels(tr, meta).failure_keyframe == meta.executed.index("s0_close")
    tr, meta = _case("incomplete_trajectory")
    assert derive_labels(tr, meta).failure_keyframe == meta.executed.index("s0_lift") + 1


def test_onset_is_the_first_sample_the_failure_shows_in_sim_time():
    """A spill that starts at a chosen sample: the onset time is that sample's, inside the onset keyframe; a
    success has none."""
    from sim_backends.labeler import SPILL_PARTICLES

    tr, meta = _case("protocol_violation")
    tr["liquid.bystander"] = [0] * len(tr["t"])
    j = meta.executed.index("s1_carry")
    start = tr["kf_end"][j] - 3  # three samples before the carry keyframe ends
    tr["liquid.outside"] = [0 if k < start else SPILL_PARTICLES + 1 for k in range(len(tr["t"]))]
    lab = derive_labels(tr, meta)
    assert lab.failure_keyframe == j and lab.onset_s == pytest.approx(tr["t"][start] - tr["t"][0])
    assert tr["t"][tr["kf_end"][j - 1]] < tr["t"][0] + lab.onset_s <= tr["t"][tr["kf_end"][j]]
    tr["liquid.outside"] = [0 if k < start + 2 else SPILL_PARTICLES + 1 for k in range(len(tr["t"]))]
    assert derive_labels(tr, meta).onset_s == pytest.approx(tr["t"][start + 2] - tr["t"][0])  # it moves with it
    tr, meta = _case("success")
    assert derive_labels(tr, meta).onset_s is None


def test_irreversible_events_are_found_where_they_happen_and_not_in_a_success():
    """The first irreversible sample: a spill where liquid leaves every vessel, a drop where the glassware falls
    fast enough to break, nothing in a success (a vessel tilted in the hand, as a pour tilts it, is no fall)."""
    from sim_backends.labeler import BREAK_SPEED, SPILL_PARTICLES, irreversible_sample

    tr, meta = _case("success")
    assert irreversible_sample(tr, meta) is None
    tr, meta = _case("protocol_violation")
    tr["liquid.bystander"] = [0] * len(tr["t"])
    start = tr["kf_end"][meta.executed.index("s1_carry")] - 3
    tr["liquid.outside"] = [0 if k < start else SPILL_PARTICLES for k in range(len(tr["t"]))]
    assert irreversible_sample(tr, meta) == (start, "spill")
    tr, meta = _case("object_slippage")  # dropped from carry height
    j, kind = irreversible_sample(tr, meta)
    z = [p[2] for p in tr["obj.pos"]]
    assert kind == "breakage" and z[j] < z[j - 1] and all(z[k] >= z[k - 1] - 1e-9 for k in range(1, j - 3))
    assert (z[j - 1] - z[j]) * RATE + 9.81 / (2 * RATE) >= BREAK_SPEED


def test_a_breaking_drop_onto_a_goal_that_holds_is_no_success():
    """Released 10 cm above its mark, the object lands there upright and let go: every goal holds, but the impact
    is a breakage (the Fatal severity's), so no success; no detector explains a drop onto the mark, so the episode is
    unexplained (left out). Released 2 cm up, it breaks nothing and succeeds. A recovery family's success agrees."""
    from sim_backends.goals import failed_goals
    from sim_backends.labeler import broken

    meta = _pick_place_meta(list(NOMINAL))
    high = {"s1_lower": (0, 0, 0.1), "s1_release": (0, 0, 0.1)}
    tr = _simulate(meta, shift=high)
    assert failed_goals(tr, meta.to_dict()) == [] and broken(tr, meta.to_dict()) == ["obj"]
    lab = derive_labels(tr, meta)
    assert not lab.success and lab.failure_type is None and lab.evidence.endswith("failed goals: obj broken")
    low = {"s1_lower": (0, 0, 0.02), "s1_release": (0, 0, 0.02)}
    assert derive_labels(_simulate(meta, shift=low), meta).success
    # a recovery family judged by goals of its own applies the same rule
    from types import SimpleNamespace

    from sim_backends.supervision.loop import TaskFamily

    family = TaskFamily("place", [], goals=meta.to_dict()["goals"])
    assert not family.success(SimpleNamespace(state_trace=tr, task_meta=meta))
    assert family.success(SimpleNamespace(state_trace=_simulate(meta, shift=low), task_meta=meta))


def test_a_vessel_rocked_out_of_the_hand_is_no_fall_unless_it_stays_tipped():
    """An open hand retreating from a placed beaker can catch its rim and rock it past UPRIGHT_TILT; it rights
    itself, which is no fall. Tipped for TIPPED_FOR (k samples after the first) it is, from the first tipped sample;
    so is a vessel still tipped where the trace ends, however short that is."""
    from sim_backends.goals import UPRIGHT_TILT
    from sim_backends.labeler import HELD, TIPPED_FOR, irreversible_sample
    from sim_backends.schema import samples_in

    base, meta = _case("success")
    k = samples_in(base, TIPPED_FOR)
    n = len(base["t"])
    # the released beaker stands still while the controller settles: 3k more samples of the last state
    for c, col in base.items():
        if isinstance(col, list) and len(col) == n:
            col.extend([col[-1]] * (3 * k))
    base["t"][n:] = [base["t"][n - 1] + (i + 1) / RATE for i in range(3 * k)]
    # the first sample the hand is HELD away from the beaker, as it rises after the release
    away = [np.linalg.norm(np.subtract(p, e)) > HELD for p, e in zip(base["obj.pos"], base["ee_pos"])]
    start = away.index(True, base["kf_end"][-2] + 1)
    assert start + k + 1 < len(base["t"]) - k
    a = UPRIGHT_TILT + 0.3
    tipped = [float(np.sin(a / 2)), 0.0, 0.0, float(np.cos(a / 2))]

    def tipped_during(first: int, last: int) -> dict:
        tr = dict(base)
        tr["obj.quat"] = [tipped if first <= i <= last else q for i, q in enumerate(base["obj.quat"])]
        return tr

    assert irreversible_sample(tipped_during(start, start + k - 1), meta) is None  # rocked, back within TIPPED_FOR
    assert irreversible_sample(tipped_during(start, start + k), meta) == (start, "fall")
    last = len(base["t"]) - 1
    assert irreversible_sample(tipped_during(last - 2, last), meta) == (last - 2, "fall")  # tipped to the end


def test_an_object_pushed_beyond_the_arms_reach_is_irreversible_where_it_leaves_it():
    """A beaker slid out of the hand to 0.95 m from the arm's base cannot be fetched back: the first sample beyond
    REACH is the event. Carried there in the hand it is no event, nor where the meta does not know the base."""
    from sim_backends.labeler import REACH, irreversible_sample

    tr, meta = _case("success")
    meta.robot_base = [0.0, 0.0, 0.0]
    assert irreversible_sample(tr, meta) is None  # it stays at 0.5-0.56 m
    start = tr["kf_end"][0] + 2  # after the reach, the hand still above the bench, away from it
    n = len(tr["t"])
    slid = [list(p) for p in tr["obj.pos"]]
    for k in range(start, n):
        slid[k] = [min(0.5 + 0.02 * (k - start), 0.95), 0.0, slid[start][2]]
    tr["obj.pos"] = slid
    j = next(k for k in range(n) if slid[k][0] > REACH)
    assert irreversible_sample(tr, meta) == (j, "out_of_reach")
    assert irreversible_sample(tr, meta.to_dict()) == (j, "out_of_reach")  # the JSON form a shard stores
    tr["ee_pos"] = [list(p) if k < start else [p[0], p[1], p[2] + 0.05] for k, p in enumerate(slid)]
    assert irreversible_sample(tr, meta) is None  # held: the hand is with it
    tr["ee_pos"] = _case("success")[0]["ee_pos"]
    far_start = [[0.95, 0.0, p[2]] for p in slid]  # beyond REACH from the first sample: never within reach
    assert irreversible_sample({**tr, "obj.pos": far_start}, meta) is None
    old_shard = meta.to_dict()
    del old_shard["robot_base"]  # task metadata written before the base was recorded
    assert irreversible_sample(tr, old_shard) is None
    meta.robot_base = None
    assert irreversible_sample(tr, meta) is None


def test_a_failure_no_detector_explains_is_not_given_a_type():
    """The object stands where the plan put it, but the goal asks for another spot: no state signature
    explains the failed goal, so the label says so instead of guessing a type."""
    tr, meta = _case("success")
    meta.places["target"] = [0.2, -0.3, 0.0]
    lab = derive_labels(tr, meta)
    assert not lab.success and lab.failure_type is None and not lab.explained
    assert lab.evidence.startswith("unexplained") and "at" in lab.evidence


def test_a_spill_is_detected_as_a_spill_with_risk_severity():
    from labrobfail_vlm.taxonomy import Severity
    from sim_backends.labeler import SPILL_PARTICLES

    tr, meta = _case("protocol_violation")
    tr["liquid.bystander"] = [0] * len(tr["t"])  # nothing reaches another vessel: it lands on the bench
    j = meta.executed.index("s1_carry")
    tr["liquid.outside"] = [0 if k < tr["kf_end"][j] else SPILL_PARTICLES + 1 for k in range(len(tr["t"]))]
    lab = derive_labels(tr, meta)
    assert lab.failure_type == "target_positioning_deviation" and "spill" in lab.evidence
    assert lab.failure_keyframe == j and lab.severity == int(Severity.RISK)  # shows at the end of s1_carry


def test_glassware_falling_fast_is_fatal():
    from labrobfail_vlm.taxonomy import Severity
    from sim_backends.labeler import BREAK_SPEED, impact_speed

    tr, meta = _case("object_slippage")  # dropped from carry height: it hits the bench at once
    assert impact_speed(tr, "obj") >= BREAK_SPEED
    assert derive_labels(tr, meta).severity == int(Severity.FATAL)
    tr, meta = _case("target_positioning_deviation")  # set down gently, only in the wrong place
    assert impact_speed(tr, "obj") < BREAK_SPEED and derive_labels(tr, meta).severity != int(Severity.FATAL)


def test_impact_speed_does_not_depend_on_where_the_impact_falls_between_samples():
    """A 10 cm free fall hits at 1.40 m/s: it reads as breaking (>= 1.2) whatever the 40 Hz sample phase,
    and never above the true impact speed; a 5 cm fall (0.99 m/s) never reads as breaking."""
    from sim_backends.labeler import BREAK_SPEED, GRAVITY, impact_speed

    for height in (0.10, 0.05):
        hit = (2 * GRAVITY * height) ** 0.5
        fall_t = hit / GRAVITY
        for phase in np.linspace(0.0, 0.024, 7):
            ts = phase + np.arange(0, 0.3, 1 / 40)
            z = [height - 0.5 * GRAVITY * min(t, fall_t) ** 2 for t in ts]
            speed = impact_speed({"obj.pos": [[0.5, 0.0, v] for v in z], "rate_hz": 40.0}, "obj")
            assert speed <= hit + 1e-9
            assert (speed >= BREAK_SPEED) == (height == 0.10), (height, phase, speed)


@pytest.mark.parametrize("how", ["on_its_side", "off_the_bench"])
def test_a_fall_carries_a_severity_that_admits_manual(how):
    """The template Q6 decoder admits MANUAL only at the severities a fall can carry (corrections.admissible):
    a vessel on its side is tipped over (Risk), one off the bench is Fatal."""
    from labrobfail_vlm.corrections import FALL_SEVERITIES, Context, choose
    from labrobfail_vlm.taxonomy import Severity
    from sim_backends.goals import object_fell
    from sim_backends.schema import meta_dict

    tr, meta = _case("target_positioning_deviation")  # set down gently in the wrong place: not a fall yet
    assert not object_fell(tr, meta_dict(meta)) and derive_labels(tr, meta).severity == int(Severity.DANGEROUS)
    last = len(tr["t"]) - 1
    if how == "on_its_side":
        tr["obj.quat"][last] = _twist(math.pi / 2)
    else:
        x, y, _ = tr["obj.pos"][last]
        tr["obj.pos"][last] = (x, y, -0.5)
    lab = derive_labels(tr, meta)
    assert object_fell(tr, meta_dict(meta)) and lab.severity in FALL_SEVERITIES
    assert choose(Context(lab.failure_type, "place", fell=True)) == "MANUAL"
