"""Each primitive of the action dictionary moves the simulated arm or gripper as specified (real PyBullet)."""

import dataclasses
import math

import numpy as np
import pytest

from labrobfail_vlm.actions import prim
from sim_backends.executor import AXES, CorrectionExecutor, yaw_aligned
from sim_backends.perturbations.control import so3_exp
from sim_backends.registry import make_backend
from sim_backends.types import matrix_to_quat, quat_to_matrix, rotation_angle


@pytest.fixture(scope="module")
def src():
    s = make_backend("pybullet", render=False)
    yield s
    s.close()


def start(src, scenario, upto=None, seed=0):
    """Reset, begin, and step the plan up to and including keyframe `upto`."""
    src.reset(scenario, seed, "seen")
    src.begin()
    for k in src.scripted_keyframes():
        if upto is None:
            break
        src.step(k)
        if k.name == upto:
            break
    if not src.executed_so_far():  # the executor corrects an episode in progress
        src.step(src.scripted_keyframes()[0])
    return src


def high(src):
    """Open gripper in the air, side orientation (away from the bench and the objects)."""
    start(src, "pick_place_beaker_small", "s0_pre")
    pre = src.scripted_keyframes()[0]
    air = dataclasses.replace(pre, pos=(0.5, 0.05, 0.25), settle_steps=200)  # mid-workspace, clear of everything
    src.step(air)
    src.step(air)  # the position controller lags: let it arrive
    return src


def state(src):
    return src.observe().state


def run(src, *prims):
    res = CorrectionExecutor(src).run(list(prims))
    assert res.executed, res
    return res


def ee(src):
    return np.asarray(state(src)["ee_pos"])


def test_hold_position_hold_gripper_hold_orientation(src):
    start(src, "pick_place_beaker_small", "s0_pre")
    p0, q0, g0 = ee(src), state(src)["ee_quat"], state(src)["grip_cmd"]
    res = run(src, prim("hold_position"), prim("hold_gripper"), prim("hold_orientation"))
    assert [e["keyframes"] for e in res.log] == [1, 0, 0]
    assert np.linalg.norm(ee(src) - p0) < 0.005
    assert rotation_angle(state(src)["ee_quat"], q0) < 0.02 and state(src)["grip_cmd"] == g0


@pytest.mark.parametrize(
    "direction, axis",
    [
        ("up", [0, 0, 1]),
        ("down", [0, 0, -1]),
        ("left", [0, 1, 0]),
        ("right", [0, -1, 0]),
        ("forward", [1, 0, 0]),
        ("backward", [-1, 0, 0]),
    ],
)
def test_delta_pos_moves_along_the_named_direction(src, direction, axis):
    high(src)  # side grasp: the approach axis is world +x
    p0 = ee(src)
    run(src, prim("delta_pos", direction=direction, dist=0.05))
    d = ee(src) - p0
    along = float(np.dot(d, axis))
    # the position-controlled arm lands within ~2.5 cm of a target (it overshoots the first move after a hold)
    assert 0.035 < along < 0.08 and np.linalg.norm(d - along * np.asarray(axis)) < 0.015, d


def test_forward_follows_a_top_down_gripper_downwards(src):
    start(src, "press_button_red", "s0_above")
    p0 = ee(src)
    run(src, prim("delta_pos", direction="forward", dist=0.03))
    assert ee(src)[2] - p0[2] == pytest.approx(-0.03, abs=0.008)


def test_oscillate_strokes_side_to_side(src):
    high(src)
    p0 = ee(src)
    ys = []
    ex = CorrectionExecutor(src)
    orig = ex._go

    def go(*a, **k):
        orig(*a, **k)
        ys.append(ee(src)[1])

    ex._go = go
    assert ex.run([prim("oscillate", axis="y", amp=0.02, n=2)]).executed
    assert len(ys) == 5 and max(ys) - min(ys) == pytest.approx(0.04, abs=0.01)
    assert np.linalg.norm(ee(src) - p0) < 0.01


def test_gripper_open_and_close(src):
    start(src, "pick_place_beaker_small", "s0_pre")
    run(src, prim("gripper_close"))
    assert state(src)["grip_cmd"] == 1 and state(src)["width"] < 0.01
    run(src, prim("gripper_open"))
    assert state(src)["grip_cmd"] == 0 and state(src)["width"] > 0.07


def test_align_to_centres_the_open_gripper_on_a_misaligned_object(src):
    start(src, "pick_place_beaker_small", "s0_pre")
    reach = src.scripted_keyframes()[1]
    src.step(dataclasses.replace(reach, pos=tuple(np.add(reach.pos, [0, 0.04, 0]))))  # beside the beaker
    run(src, prim("align_to", target_id="small beaker"))
    meta = src.task_meta(src.executed_so_far())
    goal = np.asarray(state(src)["obj.pos"]) + np.asarray(meta.steps[0].grip_offset)
    assert np.linalg.norm(ee(src)[:2] - goal[:2]) < 0.01
    run(src, prim("gripper_close"))
    assert state(src)["obj.contacts"] == 2


def test_move_above_carries_the_object_over_the_destination(src):
    start(src, "pick_place_beaker_small", "s0_lift")
    res = run(src, prim("move_above", dest_id="target area", h=0.01, obj="small beaker"), prim("gripper_open"))
    target = src.task_meta([]).places["target"]
    assert np.linalg.norm(np.asarray(state(src)["obj.pos"])[:2] - np.asarray(target[:2])) < 0.02
    assert res.log[0]["keyframes"] == 3  # lift, travel, lower


def test_move_above_grasps_an_object_that_is_not_held(src):
    start(src, "pick_place_beaker_small", "s0_pre")
    res = run(src, prim("move_above", dest_id="target area", h=0.01, obj="small beaker"))
    assert res.log[0]["note"] == "grasped first" and state(src)["obj.contacts"] > 0


def test_set_orient_levels_the_gripper_keeping_its_heading(src):
    high(src)
    run(src, prim("rotate", axis="y", angle=0.4))
    level = quat_to_matrix(src.scripted_keyframes()[0].quat)
    assert rotation_angle(state(src)["ee_quat"], src.scripted_keyframes()[0].quat) > 0.3
    run(src, prim("set_orient", roll=0.0, pitch=0.0))
    cur = quat_to_matrix(tuple(state(src)["ee_quat"]))
    assert np.allclose(yaw_aligned(level, cur), cur, atol=0.06)  # only a heading apart from the plan's level


@pytest.mark.parametrize("axis", ["x", "y"])  # (a yaw of the side gripper is where the Panda's IK is weakest)
def test_rotate_turns_about_a_world_axis(src, axis):
    high(src)
    q0 = state(src)["ee_quat"]
    run(src, prim("rotate", axis=axis, angle=0.3))
    q1 = state(src)["ee_quat"]
    assert rotation_angle(q1, q0) == pytest.approx(0.3, abs=0.06)
    turn = quat_to_matrix(tuple(q1)) @ quat_to_matrix(tuple(q0)).T  # a turn about the named world axis
    assert rotation_angle(matrix_to_quat(turn), matrix_to_quat(so3_exp(AXES[axis] * 0.3))) < 0.08


def test_move_to_pose_runs_the_omitted_step(src):
    src.reset("pick_place_beaker_small", 0, "seen")
    src.begin()
    place = [k for k in src.scripted_keyframes() if k.segment == 1]
    src.step(place[0])  # the grasp was skipped: the arm goes to carry with nothing in the hand
    res = run(src, prim("move_to_pose", pose_id="omitted:grasp"))
    assert res.log[0]["keyframes"] == 4 and state(src)["obj.contacts"] > 0
    assert [k.name for k in src.executed_so_far()][1:] == ["s0_pre", "s0_reach", "s0_close", "s0_lift"]
    assert not CorrectionExecutor(src).run([prim("move_to_pose", pose_id="omitted:grasp")]).executed
    # a pause before a return to a step that was not omitted is refused whole: the arm does not move
    before, n = state(src)["ee_pos"], len(src.executed_so_far())
    res = CorrectionExecutor(src).run([prim("hold_position"), prim("move_to_pose", pose_id="omitted:grasp")])
    assert not res.executed and res.error == "move_to_pose: no grasp step was omitted" and res.log == []
    assert len(src.executed_so_far()) == n and list(state(src)["ee_pos"]) == list(before)


def test_a_grasp_that_did_not_take_is_made_again_by_a_return_to_the_omitted_grasp(src):
    """The grasp ran 5 cm beside the beaker (as the translate injection misses it): no grasp step was skipped, but
    the plan has the beaker in the hand and the hand is empty, so "return to perform the omitted grasp" grasps it
    where it stands and names the grasp step for the policy's re-planning. Where the plan holds nothing yet (the
    fingers still open) or the hand holds it, the return is refused before anything moves, as before."""
    src.reset("pick_place_beaker_small", 0, "seen")
    src.begin()
    beside = [dataclasses.replace(k, pos=(k.pos[0], k.pos[1] + 0.05, k.pos[2])) for k in src.scripted_keyframes()]
    for k in beside[:2]:  # s0_pre, s0_reach: the fingers still open
        src.step(k)
    before, n = list(state(src)["ee_pos"]), len(src.executed_so_far())
    res = CorrectionExecutor(src).run([prim("hold_position"), prim("move_to_pose", pose_id="omitted:grasp")])
    assert not res.executed and res.error == "move_to_pose: no grasp step was omitted" and res.log == []
    assert len(src.executed_so_far()) == n and list(state(src)["ee_pos"]) == before
    src.step(beside[2])  # s0_close beside the beaker: the fingers close on nothing
    assert state(src)["obj.contacts"] == 0 and state(src)["grip_cmd"] == 1
    res = run(src, prim("hold_position"), prim("move_to_pose", pose_id="omitted:grasp"))
    assert state(src)["obj.contacts"] > 0 and res.step == 0
    assert res.log[1]["note"] == "the grasp that did not take, made again" and res.log[1]["keyframes"] >= 3
    res = CorrectionExecutor(src).run([prim("move_to_pose", pose_id="omitted:grasp")])
    assert not res.executed and res.error == "move_to_pose: no grasp step was omitted"  # now it is held


def test_a_return_to_a_grasp_is_refused_once_the_plan_has_set_the_object_down(src):
    start(src, "pick_place_beaker_small", src.scripted_keyframes()[-1].name)  # placed and released
    assert state(src)["obj.contacts"] == 0
    res = CorrectionExecutor(src).run([prim("move_to_pose", pose_id="omitted:grasp")])
    assert not res.executed and res.error == "move_to_pose: no grasp step was omitted" and res.log == []


def test_a_step_still_to_come_is_not_omitted_until_the_policy_has_stopped(src):
    """Mid-episode only a step before the current one was left out: with the plan in its grasp step, "return to
    the omitted place" is refused before anything moves (the place is to come); once the policy has stopped
    (`final`), the same return runs the place that never ran."""
    start(src, "pick_place_beaker_small", "s0_lift")  # grasped and lifted; the place step never runs
    before, n = list(state(src)["ee_pos"]), len(src.executed_so_far())
    res = CorrectionExecutor(src).run([prim("move_to_pose", pose_id="omitted:place")])
    assert not res.executed and res.error == "move_to_pose: no place step was omitted" and res.log == []
    assert len(src.executed_so_far()) == n and list(state(src)["ee_pos"]) == before
    res = CorrectionExecutor(src).run([prim("move_to_pose", pose_id="omitted:place")], final=True)
    assert res.executed and res.step == 1 and state(src)["grip_cmd"] == 0 and state(src)["obj.contacts"] == 0


def test_a_later_grasp_of_another_object_is_not_the_omitted_grasp(src):
    """pour_and_stir grasps the source, pours, sets it down, then grasps the rod. Pouring with the source in the
    hand, "return to perform the omitted grasp" names no grasp that was left out: the rod's is to come and the
    source's took. It is refused before anything moves (it used to send the arm to the rod)."""
    scenario = first_of(src, "pour_and_stir")
    src.reset(scenario, 0, "seen")
    src.begin()
    for k in src.scripted_keyframes():
        src.step(k)
        if k.segment == 1:  # the first keyframe of the pour
            break
    assert state(src)["src.contacts"] > 0
    n = len(src.executed_so_far())
    res = CorrectionExecutor(src).run([prim("move_to_pose", pose_id="omitted:grasp")])
    assert not res.executed and res.error == "move_to_pose: no grasp step was omitted" and res.log == []
    assert len(src.executed_so_far()) == n


def first_of(src, template):
    """The first scenario of a template (scenario names change as the catalogue grows)."""
    return next(s for s in src.scenarios() if src.scenario_info(s)["template"] == template)


def test_an_omitted_pour_picks_the_vessel_up_again_and_pours(src):
    """The pour was skipped and the source set back full: returning to the omitted pour grasps it first."""
    src.reset(first_of(src, "pour"), 0, "seen")
    src.begin()
    for k in src.scripted_keyframes():
        if k.segment != 1:  # grasp, then the place step straight away: lifted and set back unpoured
            src.step(k)
    assert state(src)["src.contacts"] == 0 and state(src)["liquid.dest"] == 0
    res = run(src, prim("move_to_pose", pose_id="omitted:pour"))
    assert res.log[0]["keyframes"] > 4 and state(src)["liquid.dest"] > 0
    assert state(src)["src.contacts"] > 0  # still in the hand after the pour: the policy sets it back


def test_align_above_and_tilt_pour_empty_the_source(src):
    start(src, first_of(src, "pour"), "s0_lift")
    labels = src.task_meta([]).labels
    run(src, prim("align_above", src=labels["src"], dest=labels["dest"]))
    pour = [k for k in src.scripted_keyframes() if k.name == "s1_lower"][0]
    assert np.linalg.norm(ee(src) - np.asarray(pour.pos)) < 0.01
    before = state(src)["liquid.src"]
    run(src, prim("tilt_pour", angle=2.0, v=0.6))
    assert state(src)["liquid.src"] <= before // 4 and state(src)["liquid.dest"] > 0
    assert rotation_angle(state(src)["ee_quat"], pour.quat) < 0.1  # back upright


def test_pulling_a_held_handle_until_the_door_is_open(src):
    start(src, "open_oven_center", "s0_arc1")
    res = run(src, prim("gripper_close"), prim("delta_pos", direction="backward", dist=0.4, until="door_open"))
    assert state(src)["oven.q"] >= 1.1 and res.log[1]["note"] == "condition met"


def test_align_to_a_door_handle_then_open(src):
    src.reset("open_oven_center", 0, "seen")
    src.begin()
    kfs = src.scripted_keyframes()
    src.step(kfs[0])
    run(
        src,
        prim("align_to", target_id="door handle"),
        prim("gripper_close"),
        prim("delta_pos", direction="backward", dist=0.4, until="door_open"),
    )
    assert state(src)["oven.q"] >= 1.1


def test_press_until_pressed(src):
    start(src, "press_button_red", "s0_above")
    run(
        src,
        prim("align_to", target_id="red button"),
        prim("delta_pos", direction="forward", dist=0.03, until="pressed"),
    )
    assert state(src)["button.q"] >= 0.007


def test_unrunnable_corrections_are_refused_with_a_reason(src):
    start(src, "pick_place_beaker_small", "s0_pre")
    res = CorrectionExecutor(src).run([prim("manual", phrase="wipe bench")])
    assert not res.executed and res.manual == ["wipe bench"] and res.keyframes == 0
    res = CorrectionExecutor(src).run([prim("align_to", target_id="pipette")])
    assert not res.executed and "no object or place called 'pipette'" in res.error
    res = CorrectionExecutor(src).run([prim("delta_pos", direction="sideways", dist=0.1)])
    assert "unknown direction" in res.error
    assert "unknown primitive" in CorrectionExecutor(src).run([{"op": "teleport", "args": {}}]).error
    assert not math.isnan(ee(src)[0])
    # a model's correction may name a fixed device as the thing to carry: refused before the arm moves
    start(src, "open_oven_center", "s0_arc1")
    before = ee(src)
    res = CorrectionExecutor(src).run([prim("move_above", obj="drying oven", dest_id="its original position", h=0.01)])
    assert not res.executed and res.keyframes == 0 and "cannot carry 'oven': the oven is fixed" in res.error
    assert np.allclose(ee(src), before)


def test_a_regrasp_in_a_pour_goes_on_with_the_pour_not_the_set_back(src):
    """A pour sets the vessel back where it grasped it, so after a regrasp the arm stands as near the set-back as
    the grasp; the correction names the step it redid, and the re-planned pour lifts, pours and succeeds."""
    from sim_backends.policies.scripted import resume_index

    start(src, first_of(src, "pour"), "s0_pre")
    plan = src.scripted_keyframes()
    for k in plan[1:3]:  # reach and close 4 cm beside the vessel: the fingers close on nothing
        src.step(dataclasses.replace(k, pos=tuple(np.add(k.pos, [0, 0.04, 0]))))
    assert state(src)["width"] < 0.01
    label = src.task_meta([]).labels["src"]
    res = run(src, prim("gripper_open"), prim("align_to", target_id=label), prim("gripper_close"))
    assert res.step == 0 and state(src)["width"] > 0.03  # the grasp step, redone: the vessel is held
    assert plan[resume_index(plan, state(src))].name == "s2_release"  # without the step: the set-back's release
    i = resume_index(plan, state(src), res.step)
    assert plan[i].name == "s0_lift"
    for k in plan[i:]:
        src.step(k)
    assert src.finish().labels.success
