"""LabRobFail-Sim's scenario catalogue (configs/tasks/pybullet.yaml): size, horizons, and perturbations that
name only keyframes, steps and objects the scenario's plan has (a typo would stop a long generation run)."""

from collections import Counter

import pytest

from labrobfail_vlm.taxonomy import ATOMIC_ACTIONS, horizon_of
from sim_backends import make_backend


@pytest.fixture(scope="module")
def plans():
    src = make_backend("pybullet", render=False, max_distractors=0)
    out = {}
    try:
        for sc in src.scenarios():
            src.reset(sc, 0, "seen")
            out[sc] = (src.scripted_keyframes(), src.scenario_info(sc), set(src.object_positions()))
    finally:
        src.close()
    return out


def test_catalogue_covers_the_paper_scale(plans):
    assert len(plans) >= 72
    horizons = Counter(horizon_of(len(kfs)) for kfs, _, _ in plans.values())
    assert set(horizons) == {"short", "medium", "long"}
    # Medium and long tasks are oversampled (repeat) or outnumber the short ones.
    weight = Counter()
    for kfs, info, _ in plans.values():
        weight[horizon_of(len(kfs))] += info["repeat"]
    assert weight["medium"] + weight["long"] >= 1.5 * weight["short"] and weight["long"] >= 2 * sum(
        horizon_of(len(k)) == "long" for k, _, _ in plans.values()
    )
    actions = {k.action for kfs, _, _ in plans.values() for k in kfs}
    assert actions == set(ATOMIC_ACTIONS)


def test_every_perturbation_names_what_its_plan_has(plans):
    for sc, (kfs, info, places) in plans.items():
        names, steps = {k.name for k in kfs}, {k.segment for k in kfs}
        assert info["perturbations"], sc
        for spec in info["perturbations"]:
            kf = set(spec.get("keyframes", [])) | set(spec.get("at", []))
            assert kf <= names, (sc, sorted(kf - names))
            st = {spec["step"]} if "step" in spec else set(spec.get("steps", []))
            assert st <= steps, (sc, st)
            assert spec.get("to") is None or spec["to"] in places, (sc, spec["to"])


def test_the_nominal_arm_never_touches_a_distractor():
    """Distractors stand clear of where the arm's links pass along the nominal plan (Panda.sweep): these seeds
    put one in the forearm's or hand's way before the sweep existed (each was a nominal failure)."""
    import pybullet as p

    from sim_backends.generate import pair_seed

    src = make_backend("pybullet", render=False, max_distractors=3)
    names = src.scenarios()
    cases = [
        ("pick_place_beaker_large", 8),
        ("pick_place_far_flask", 7 * names.index("pick_place_far_flask")),
        ("open_oven_left", 7 * names.index("open_oven_left") + 2),
        ("pick_place_right_beaker_small", 7 * names.index("pick_place_right_beaker_small") + 1000),
    ]
    try:
        placed = 0
        for sc, pair in cases:
            src.reset(sc, pair_seed(0, pair, 0), "seen")

            def where():
                return {
                    d: p.getBasePositionAndOrientation(b, physicsClientId=src.cid)[0]
                    for d, b in src.scene.distractors.items()
                }

            before = where()
            ep = src.execute(src.scripted_keyframes())
            placed += len(before)
            for d, pos in where().items():  # nothing pushed them
                assert max(abs(a - b) for a, b in zip(pos, before[d])) < 0.005, (sc, d)
            assert ep.labels.success, (sc, ep.labels.evidence)
        assert placed >= 3  # the seeds still draw distractors: they now stand elsewhere
    finally:
        src.close()
