"""The paper's contract tables and the backend-agnostic perturbation operators."""

from collections import Counter

import numpy as np
import pytest

from labrobfail_vlm.taxonomy import (
    ATOMIC_ACTIONS,
    FAILURE_TYPES,
    HELD_OUT_SPLITS,
    SCENE_VARIANTS,
    SEALED_SPLITS,
    Category,
    Severity,
    check_variant,
    horizon_of,
    object_set,
    scene_set,
)
from sim_backends.perturbations import control, physics, semantic
from sim_backends.types import Keyframe, matrix_to_quat, quat_to_matrix, rotation_angle


def test_taxonomy_matches_paper():
    assert len(FAILURE_TYPES) == 11
    per_cat = Counter(ft.category for ft in FAILURE_TYPES.values())
    assert per_cat == {
        Category.SAFETY: 2,
        Category.LOGIC: 2,
        Category.MOTION: 2,
        Category.GRASPING: 2,
        Category.PERCEPTION: 3,
    }
    assert [c.value for c in Category] == [1, 2, 3, 4, 5] and Category.PERCEPTION.title == "Perception Failure"
    assert [s.title for s in Severity] == ["Risk Level", "Dangerous Level", "Fatal Level", "Management Incident"]
    assert [s.main_text for s in Severity] == ["Minor", "Recoverable", "Critical", "Catastrophic"]
    assert Severity(2).display == "Dangerous Level (option 2; the paper's main text: Recoverable)"
    assert ATOMIC_ACTIONS == ("grasp", "place", "open", "close", "pour", "shake", "insert", "stir")
    assert [horizon_of(n) for n in (10, 11, 30, 31)] == ["short", "medium", "medium", "long"]


def test_each_variant_holds_out_what_its_name_says():
    # the paper's four generalisation settings (seen, objects, scene, both held out), each held-out one twice: a
    # validation set from the val catalogue and family, a sealed test set from the sealed ones
    held = {v: (object_set(v), scene_set(v)) for v in SCENE_VARIANTS}
    assert held == {
        "seen": ("seen", "seen"),
        "val_object": ("val", "seen"),
        "val_scene": ("seen", "val"),
        "val_both": ("val", "val"),
        "test_object": ("sealed", "seen"),
        "test_scene": ("seen", "sealed"),
        "test_both": ("sealed", "sealed"),
    }
    assert set(HELD_OUT_SPLITS) == {v for v, h in held.items() if h != ("seen", "seen")}
    assert set(SEALED_SPLITS) == {v for v, h in held.items() if "sealed" in h}
    with pytest.raises(ValueError, match="variant: 'unseen_both' was renamed; use val_both"):
        check_variant("unseen_both")


def _kfs():
    q = (1.0, 0.0, 0.0, 0.0)
    return [
        Keyframe(f"s{s}_k{i}", (0.1 * i, 0.0, 0.2), q, int(i == 1), "obj", s, "grasp")
        for s in range(3)
        for i in range(3)
    ]


def test_so3_exp_and_quaternions():
    rng = np.random.default_rng(0)
    for _ in range(20):
        xi = rng.normal(size=3)
        R = control.so3_exp(xi)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.isclose(np.linalg.det(R), 1.0)
        q = matrix_to_quat(R)
        assert np.allclose(quat_to_matrix(q), R, atol=1e-9)
        assert np.isclose(
            rotation_angle(q, (0, 0, 0, 1)),
            min(np.linalg.norm(xi) % (2 * np.pi), 2 * np.pi - np.linalg.norm(xi) % (2 * np.pi)),
            atol=1e-6,
        )


def test_control_operators_touch_only_named_keyframes():
    kfs, rng = _kfs(), np.random.default_rng(1)
    out, prov = control.translate(kfs, ["s1_k1"], [0.05, 0.05, 0.0], rng, min_norm=0.03)
    moved = [a.name for a, b in zip(kfs, out) if a.pos != b.pos]
    assert moved == ["s1_k1"] and np.linalg.norm(prov["xi_trans"]) >= 0.03
    out, prov = control.rotate(kfs, ["s0_k2"], [0.5, 0, 0], rng, min_norm=0.3)
    assert rotation_angle(out[2].quat, kfs[2].quat) == pytest.approx(np.linalg.norm(prov["xi_rot"]), abs=1e-4)
    out, prov = control.corrupt_gripper(kfs, ["s1_k1"], 1.0, rng)
    assert prov["flipped"] == [{"keyframe": "s1_k1", "to": "open"}] and out[4].gripper == 0 and out[1].gripper == 1
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
    ev, _ = physics.sample_event(kfs, "friction", "obj", ["s1_k0"], 0.5, rng)
    assert 0.5 <= ev.scale <= 1.5 and ev.at_keyframe == 3
    with pytest.raises(ValueError, match="unknown parameter"):
        physics.sample_event(kfs, "gravity", "obj", ["s1_k0"], 0.5, rng)
    with pytest.raises(ValueError, match="does not have"):
        semantic.omit(kfs, 7)


def test_a_physics_perturbation_record_replays_to_its_events():
    """What the generator stores in a shard's `perturbation` column gives back the events it applied (the
    executable-correction replay depends on it), for a several-parameter draw and an old one-event record."""
    import json

    from sim_backends.failure_generator import apply_spec

    spec = {
        "level": "physics",
        "at": ["s1_k0"],
        "params": [
            {"param": "grip_force", "target": "robot", "alpha": 0.9},
            {"param": "friction", "target": "obj", "alpha": 0.5},
        ],
    }
    _, events, record = apply_spec(spec, _kfs(), {}, np.random.default_rng(4))
    assert len(events) == 2 and physics.events_from_record(json.loads(json.dumps(record))) == events
    old = {"level": "physics", "param": "mass", "target": "obj", "scale": 1.2, "at_keyframe": 3}
    assert physics.events_from_record(old) == [physics.PhysicsEvent("mass", "obj", 1.2, 3)]
    assert physics.events_from_record({"level": "control", "op": "translate"}) == []
    with pytest.raises(ValueError, match="lacks"):
        physics.events_from_record({"level": "physics", "events": [{"param": "mass"}]})


# ---- the paper's draws (Eq. 1 and 2), seeded ------------------------------------------------------------
def test_physics_delta_is_uniform_on_both_sides():
    """psi~ = psi (1 + delta), delta ~ U(-alpha, alpha): both signs, the whole range, a uniform histogram."""
    kfs, rng = _kfs(), np.random.default_rng(7)
    d = np.array([physics.sample_event(kfs, "mass", "obj", ["s1_k0"], 0.8, rng)[0].scale - 1 for _ in range(4000)])
    assert d.min() >= -0.8 and d.max() <= 0.8 and d.min() < -0.78 and d.max() > 0.78
    assert abs(float(np.mean(d > 0)) - 0.5) < 0.03  # as many heavier as lighter objects
    hist, _ = np.histogram(d, bins=8, range=(-0.8, 0.8))
    assert hist.min() > 0.8 * 4000 / 8 and hist.max() < 1.2 * 4000 / 8
    with pytest.raises(ValueError, match="alpha"):
        physics.sample_events(kfs, {"at": ["s1_k0"], "param": "mass", "target": "obj", "delta": [-0.9, -0.5]}, rng)
    with pytest.raises(ValueError, match=r"\[0, 1\)"):
        physics.alpha_of({"param": "mass", "alpha": 1.0})


def test_control_noise_is_the_papers_gaussian_and_the_filter_is_counted():
    """xi ~ N(0, diag(sigma^2)) without a filter (no draw rejected, the per-axis std is sigma); min_norm redraws
    the short ones and says how many it rejected."""
    kfs, rng = _kfs(), np.random.default_rng(8)
    sig = [0.04, 0.02, 0.0]
    draws = [control.translate(kfs, ["s1_k1"], sig, rng)[1] for _ in range(3000)]
    xi = np.array([p["xi_trans"] for p in draws])
    assert all(p["rejected"] == 0 for p in draws)
    assert np.allclose(xi.std(0), sig, atol=0.003) and np.allclose(xi.mean(0), 0, atol=0.003)
    assert float(np.mean(np.linalg.norm(xi, axis=1) < 0.03)) > 0.4  # short draws are kept, as the paper has it
    filt = [control.translate(kfs, ["s1_k1"], sig, rng, min_norm=0.03)[1] for _ in range(500)]
    assert all(np.linalg.norm(p["xi_trans"]) >= 0.03 for p in filt)
    assert sum(p["rejected"] for p in filt) > 300 and all(p["min_norm"] == 0.03 for p in filt)


def test_gripper_faults_per_command_both_ways():
    """Each named command is one Bernoulli(lambda) trial; closed commands open and open commands close, and a
    fault holds to the end of its segment."""
    kfs, rng = _kfs(), np.random.default_rng(9)
    # s0_k1 is closed (1), s1_k2 open (0) in _kfs
    assert kfs[1].gripper == 1 and kfs[5].gripper == 0
    to = {"open": 0, "closed": 0}
    none = 0
    for _ in range(2000):
        out, prov = control.corrupt_gripper(kfs, ["s0_k1", "s1_k2"], 0.3, rng)
        for f in prov["flipped"]:
            to[f["to"]] += 1
            k = next(i for i, x in enumerate(kfs) if x.name == f["keyframe"])
            assert out[k].gripper == 1 - kfs[k].gripper
            assert all(o.gripper == out[k].gripper for o in out[k:] if o.segment == kfs[k].segment)
        none += not prov["flipped"]
    assert abs(to["open"] / 2000 - 0.3) < 0.04 and abs(to["closed"] / 2000 - 0.3) < 0.04
    assert abs(none / 2000 - 0.49) < 0.04  # (1 - lambda)^2: no fault at all, a labelled success
    assert control.corrupt_gripper(kfs, ["s0_k1", "s1_k2"], 0.0, rng)[1]["flipped"] == []
    with pytest.raises(ValueError, match="lambda"):
        control.corrupt_gripper(kfs, ["s0_k1"], 1.5, rng)
