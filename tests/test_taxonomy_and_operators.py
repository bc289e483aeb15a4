"""The paper's contract tables and the backend-agnostic perturbation operators."""

from collections import Counter

import numpy as np
import pytest

from labrobfail_vlm.taxonomy import ATOMIC_ACTIONS, FAILURE_TYPES, Category, Severity, horizon_of
from sim_backends.perturbations import control, physics, semantic
from sim_backends.types import Keyframe, matrix_to_quat, quat_to_matrix, rotation_angle


def test_taxonomy_matches_paper():
    assert len(FAILURE_TYPES) == 11
    per_cat = Counter(ft.category for ft in FAILURE_TYPES.values())
    assert per_cat == {Category.SAFETY: 2, Category.LOGIC: 2, Category.MOTION: 2, Category.GRASPING: 2,
                       Category.PERCEPTION: 3}
    assert [c.value for c in Category] == [1, 2, 3, 4, 5] and Category.PERCEPTION.title == "Perception Failure"
    assert [s.title for s in Severity] == ["Risk Level", "Dangerous Level", "Fatal Level", "Management Incident"]
    assert ATOMIC_ACTIONS == ("grasp", "place", "open", "close", "pour", "shake", "insert", "stir")
    assert [horizon_of(n) for n in (10, 11, 30, 31)] == ["short", "medium", "medium", "long"]


def _kfs():
    q = (1.0, 0.0, 0.0, 0.0)
    return [Keyframe(f"s{s}_k{i}", (0.1 * i, 0.0, 0.2), q, int(i == 1), "obj", s, "grasp")
            for s in range(3) for i in range(3)]


def test_so3_exp_and_quaternions():
    rng = np.random.default_rng(0)
    for _ in range(20):
        xi = rng.normal(size=3)
        R = control.so3_exp(xi)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.isclose(np.linalg.det(R), 1.0)
        q = matrix_to_quat(R)
        assert np.allclose(quat_to_matrix(q), R, atol=1e-9)
        assert np.isclose(rotation_angle(q, (0, 0, 0, 1)), min(np.linalg.norm(xi) % (2 * np.pi),
                                                                 2 * np.pi - np.linalg.norm(xi) % (2 * np.pi)),
                          atol=1e-6)


def test_control_operators_touch_only_named_keyframes():
    kfs, rng = _kfs(), np.random.default_rng(1)
    out, prov = control.translate(kfs, ["s1_k1"], [0.05, 0.05, 0.0], rng, min_norm=0.03)
    moved = [a.name for a, b in zip(kfs, out) if a.pos != b.pos]
    assert moved == ["s1_k1"] and np.linalg.norm(prov["xi_trans"]) >= 0.03
    out, prov = control.rotate(kfs, ["s0_k2"], [0.5, 0, 0], rng, min_norm=0.3)
    assert rotation_angle(out[2].quat, kfs[2].quat) == pytest.approx(np.linalg.norm(prov["xi_rot"]), abs=1e-4)
    out, prov = control.corrupt_gripper(kfs, ["s1_k1"], 1.0, rng)
    assert prov["flipped"] == ["s1_k1"] and out[4].gripper == 0 and out[1].gripper == 1
    out, prov = control.truncate(kfs, ["s2_k0"], rng)
    assert len(out) == len(kfs) and all(k.pos == kfs[5].pos for k in out[6:])


def test_semantic_and_physics_operators():
    kfs, rng = _kfs(), np.random.default_rng(2)
    out, _ = semantic.permute(kfs, 0, 2)
    assert [k.segment for k in out] == [2, 2, 2, 1, 1, 1, 0, 0, 0]
    out, _ = semantic.omit(kfs, 1)
    assert 1 not in {k.segment for k in out}
    out, _ = semantic.substitute_target(kfs, 2, "other", {"obj": (0, 0, 0), "other": (0.0, 0.3, 0.5)})
    assert all(np.isclose(b.pos[1] - a.pos[1], 0.3) and b.pos[2] == a.pos[2] for a, b in zip(kfs[6:], out[6:]))
    ev, _ = physics.sample_event(kfs, "friction", "obj", ["s1_k0"], [-0.5, -0.4], rng)
    assert 0.5 <= ev.scale <= 0.6 and ev.at_keyframe == 3
    with pytest.raises(ValueError, match="unknown parameter"):
        physics.sample_event(kfs, "gravity", "obj", ["s1_k0"], [-0.5, 0.5], rng)
    with pytest.raises(ValueError, match="does not have"):
        semantic.omit(kfs, 7)


def test_a_physics_perturbation_record_replays_to_its_events():
    """What the generator stores in a shard's `perturbation` column gives back the events it applied (the
    executable-correction replay depends on it), for a several-parameter draw and an old one-event record."""
    import json

    from sim_backends.failure_generator import apply_spec
    spec = {"level": "physics", "at": ["s1_k0"], "params": [{"param": "grip_force", "target": "robot", "alpha": 0.9},
                                                            {"param": "friction", "target": "obj", "delta": [-0.5, 0]}]}
    _, events, record = apply_spec(spec, _kfs(), {}, np.random.default_rng(4))
    assert len(events) == 2 and physics.events_from_record(json.loads(json.dumps(record))) == events
    old = {"level": "physics", "param": "mass", "target": "obj", "scale": 1.2, "at_keyframe": 3}
    assert physics.events_from_record(old) == [physics.PhysicsEvent("mass", "obj", 1.2, 3)]
    assert physics.events_from_record({"level": "control", "op": "translate"}) == []
    with pytest.raises(ValueError, match="lacks"):
        physics.events_from_record({"level": "physics", "events": [{"param": "mass"}]})
