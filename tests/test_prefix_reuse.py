"""Prefix reuse (physics preset `prefix`, sim_backends/prefix.py): a pair's injected run starts from its nominal
run's saved state where the two plans part. What must hold: the nominal run is the reference run byte for byte, the
injected run takes the nominal's images and trace before the parting point and simulates only after it, a pair comes
out the same whatever ran before it, only what may be shared is shared, any run but the planned one finds the world
rebuilt, and a rewound world shows a button's lamp unlit."""

import dataclasses
import hashlib
import json

import pybullet as p
import pytest

from sim_backends import make_backend
from sim_backends.failure_generator import run_injected, run_nominal
from sim_backends.generate import pair_seed
from sim_backends.perturbations.physics import PhysicsEvent
from sim_backends.prefix import shared_prefix
from sim_backends.pybullet.robot import DT
from sim_backends.pybullet.trace import TRACE_EVERY
from sim_backends.types import Keyframe

SCENARIO, PAIR = "pick_place_right_bottle", 11  # its first draw translates a keyframe after four shared ones


def _digest(ep) -> str:
    h = hashlib.sha256(json.dumps(ep.state_trace, sort_keys=True).encode())
    for view in ep.images:
        for png in view:
            h.update(png)
    return h.hexdigest()


def _source(physics: str, **kw):
    src = make_backend("pybullet", image_size=64, physics=physics, **kw)
    src.render_frames = 8
    return src


def _pair(src, scenario: str = SCENARIO, pair: int = PAIR):
    seed = pair_seed(0, pair, 0, "seen")
    return run_nominal(src, scenario, seed, "seen", then_draw=0), run_injected(src, scenario, seed, "seen")


def _kf(name: str, x: float = 0.0, segment: int = 0) -> Keyframe:
    return Keyframe(name, (x, 0.0, 0.1), (0.0, 0.0, 0.0, 1.0), 0, "obj", segment, "pick")


def test_what_a_run_may_take_from_another():
    a = [_kf(f"k{i}", segment=i) for i in range(6)]
    moved = [*a[:3], dataclasses.replace(a[3], pos=(0.05, 0.0, 0.1)), *a[4:]]
    assert shared_prefix(a, None, moved, None) == 3  # up to the first keyframe that differs
    assert shared_prefix(a, None, moved, None, [PhysicsEvent("friction", "obj", 0.5, 2)]) == 2  # an event fires first
    assert shared_prefix(a, None, list(a), None) == 5  # never the last keyframe (drawn again after the settling)
    assert shared_prefix(a, {0, 2, 4}, moved, {0, 2, 5}) == 3  # the same ones rendered before the parting point
    assert shared_prefix(a, {0, 2, 4}, moved, {0, 1, 5}) == 1  # ... or only up to where the renders agree
    assert shared_prefix(a, None, [], None) == 0


@pytest.mark.slow  # episodes by the dozen
def test_the_injected_run_starts_where_the_plans_part_and_a_pair_is_self_contained():
    ref = _source("reference")
    try:
        ref_nominal, ref_injected = _pair(ref)
    finally:
        ref.close()
    src = _source("prefix")
    steps = {"n": 0}
    real_step = p.stepSimulation

    def counting_step(*a, **kw):  # the real step, counted
        steps["n"] += 1
        return real_step(*a, **kw)

    try:
        _pair(src, "press_button_blue", 3)  # another pair first: what it leaves behind must not reach the next
        seed = pair_seed(0, PAIR, 0, "seen")
        nominal = run_nominal(src, SCENARIO, seed, "seen", then_draw=0)
        p.stepSimulation = counting_step
        try:
            injected = run_injected(src, SCENARIO, seed, "seen")
        finally:
            p.stepSimulation = real_step
        again = _pair(src)
    finally:
        src.close()
    k = next(i for i, (a, b) in enumerate(zip(injected.executed_keyframes, nominal.executed_keyframes)) if a != b)
    assert k == 4 and _digest(nominal) == _digest(ref_nominal)  # the nominal run is reference's, byte for byte
    end = nominal.state_trace["kf_end"][k - 1]
    for col in ("t", "ee_pos", "width", "obj.pos"):
        assert injected.state_trace[col][: end + 1] == nominal.state_trace[col][: end + 1]
    for view in range(len(nominal.images)):
        assert injected.images[view][:k] == nominal.images[view][:k]
    assert any(png for png in injected.images[0][:k])  # ... and some of them are pictures
    # physics only after the parting point: the rewind skips the build's settling and the shared keyframes
    t = injected.state_trace["t"]
    after = round((t[-1] - t[end]) / DT)
    assert after <= steps["n"] <= after + TRACE_EVERY  # the trace's last sample may precede the last step
    assert injected.labels.failure_type == ref_injected.labels.failure_type
    assert [_digest(e) for e in again] == [_digest(nominal), _digest(injected)]  # the same pair, the same bytes


@pytest.mark.slow  # episodes by the dozen
def test_a_rewound_world_shows_the_lamp_unlit():
    """press_button's nominal run lights the lamp; the injected run's world is rewound to before the press."""
    seed = pair_seed(0, 3, 0, "seen")
    src, fresh = _source("prefix", button_lamp=True), _source("reference", button_lamp=True)
    try:
        nominal = run_nominal(src, "press_button_blue", seed, "seen", then_draw=0)
        assert nominal.labels.success and src._lit  # the press lit it
        src.reset("press_button_blue", seed, "seen")
        assert src._prefix is not None and src._prefix.armed  # rewound, not rebuilt
        fresh.reset("press_button_blue", seed, "seen")
        assert [im.tobytes() for im in src.render()] == [im.tobytes() for im in fresh.render()]
    finally:
        src.close()
        fresh.close()


def _by_hand(src, seed: int) -> str:
    """The nominal run stepped keyframe by keyframe (as supervision steps), its trace."""
    src.reset(SCENARIO, seed, "seen")
    src.begin(render=set())
    for kf in src.scripted_keyframes():
        src.step(kf)
    return json.dumps(src.finish().state_trace, sort_keys=True)


@pytest.mark.slow  # episodes by the dozen
def test_any_run_but_the_planned_one_finds_the_world_rebuilt():
    """After a recorded nominal run, the same nominal run again (through execute, or stepped by hand) is the
    reference run, not a continuation of a world rewound for the injected run."""
    seed = pair_seed(0, PAIR, 0, "seen")
    ref = _source("reference")
    try:
        want, want_by_hand = _digest(run_nominal(ref, SCENARIO, seed, "seen")), _by_hand(ref, seed)
    finally:
        ref.close()
    src = _source("prefix")
    try:
        run_nominal(src, SCENARIO, seed, "seen", then_draw=0)
        assert src._prefix is not None
        assert _digest(run_nominal(src, SCENARIO, seed, "seen")) == want
        run_nominal(src, SCENARIO, seed, "seen", then_draw=0)
        assert _by_hand(src, seed) == want_by_hand
        assert src._prefix is None
    finally:
        src.close()


@pytest.mark.parametrize("physics", ["reference", "fast"])
def test_presets_without_reuse_save_nothing(physics):
    src = _source(physics)
    try:
        _pair(src)
        assert src._prefix is None and not src.reuse_prefix
    finally:
        src.close()
