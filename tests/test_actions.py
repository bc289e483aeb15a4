"""The Action Dictionary: every correction template of the paper's strategy table maps to primitives."""

import pytest

from labrobfail_vlm.actions import PRIMITIVES, clauses, executable, format_primitive, to_primitives
from labrobfail_vlm.corrections import STRATEGIES, Context, candidates, choose, strategies_of
from labrobfail_vlm.questions import NO_CORRECTION

SCENE = [
    "small beaker",
    "target area",
    "drying oven",
    "Erlenmeyer flask",
    "large beaker",
    "glass rod",
    "hole 1 of the test tube rack",
    "red button",
]


def ops(text, objects=SCENE):
    return [p["op"] for p in to_primitives(text, objects)]


def test_every_filled_template_maps_without_manual_phrases():
    cands = candidates(SCENE)
    assert {sid for sid, _ in cands} == set(STRATEGIES)
    for sid, text in cands:
        prims = to_primitives(text, SCENE)
        if sid == "MANUAL":
            assert [p["op"] for p in prims] == ["manual"]
        else:
            assert executable(prims), (sid, text, prims)
            assert all(p["op"] in PRIMITIVES for p in prims)


def test_no_candidate_moves_an_object_onto_itself():
    """A correction never names one object as both what is moved and where it goes: in no candidate does a
    move_above/place primitive's destination equal the object it moves."""
    for sid, text in candidates(SCENE):
        for p in to_primitives(text, SCENE):
            moved = p.get("obj") or p.get("target_id")
            assert not (moved and p.get("dest_id") == moved), (sid, text, p)
    assert "the small beaker above the small beaker" not in " ".join(t for _, t in candidates(SCENE))


def test_a_category_narrows_the_templates_to_its_own_strategies():
    """Every strategy the rule gives a failure type lies in its category's set, the sets cover the table, and a
    category's candidates are exactly its strategies (MANUAL in each: a fall is possible in any category)."""
    from labrobfail_vlm.taxonomy import ATOMIC_ACTIONS, FAILURE_TYPES, Category

    for ft in FAILURE_TYPES.values():
        for act in ATOMIC_ACTIONS:
            for dev in ("", "door", "button"):
                assert choose(Context(ft.name, act, dev)) in strategies_of(ft.category)
    assert set().union(*(strategies_of(c) for c in Category)) == set(STRATEGIES)
    assert strategies_of(Category.LOGIC) == {"L1", "L2", "MANUAL"}
    assert "L2" not in strategies_of(Category.GRASPING) | strategies_of(Category.PERCEPTION)
    for c in Category:
        assert {sid for sid, _ in candidates(SCENE, c)} == strategies_of(c)
        assert set(candidates(SCENE, c)) <= set(candidates(SCENE))
    with pytest.raises(ValueError, match="category"):
        strategies_of(9)


def test_a_severity_narrows_the_templates_to_the_strategies_the_rule_gives_it():
    """MANUAL is the rule's answer to a fall or a Fatal failure: a Fatal answer admits only MANUAL, a Dangerous or
    Management-incident answer never admits it, a Risk answer (a vessel tipped over) admits both."""
    from labrobfail_vlm.corrections import admissible
    from labrobfail_vlm.taxonomy import Category, Severity

    for c in (None, *Category):
        every = admissible(c)
        assert admissible(c, Severity.FATAL) == {"MANUAL"}
        assert admissible(c, Severity.RISK) == every
        for sev in (Severity.DANGEROUS, Severity.MANAGEMENT_INCIDENT):
            assert admissible(c, sev) == every - {"MANUAL"} and admissible(c, sev)
            assert {sid for sid, _ in candidates(SCENE, c, sev)} == every - {"MANUAL"}
    assert admissible(Category.GRASPING, Severity.DANGEROUS) == {"G1", "G3", "P1"}


@pytest.mark.parametrize(
    "sid, want",
    [
        ("S1", ["hold_position", "hold_gripper", "set_orient"]),
        ("S2", ["set_orient", "move_above", "gripper_open"]),
        ("L1", ["gripper_open", "align_to", "gripper_close", "move_above", "gripper_open"]),
        ("L2", ["hold_position", "move_to_pose"]),
        ("M1", ["set_orient", "gripper_close", "delta_pos"]),
        ("M2", ["gripper_close", "hold_orientation", "oscillate"]),
        ("M3", ["gripper_close", "delta_pos"]),
        ("M4", ["align_above", "gripper_close", "tilt_pour"]),
        ("G1", ["gripper_open", "align_to", "gripper_close"]),
        ("G2", ["align_to", "set_orient", "gripper_open", "align_to", "gripper_close"]),
        ("G3", ["gripper_close", "move_above", "set_orient"]),
        ("P1", ["align_to", "gripper_close", "delta_pos"]),
        ("P2", ["move_above", "set_orient", "gripper_open"]),
        ("P3", ["align_to", "gripper_close", "delta_pos"]),
        ("P4", ["gripper_open", "align_to", "gripper_close"]),
    ],
)
def test_each_strategy_maps_to_the_paper_primitives(sid, want):
    text = next(t for s, t in candidates(SCENE) if s == sid)
    assert ops(text) == want


def test_placeholders_resolve_to_scene_names_and_arguments():
    p = to_primitives(
        "Move the robotic arm to position the small beaker above the target area, keep the gripper "
        "orientation horizontal, then open the gripper to release.",
        SCENE,
    )
    assert p[0] == {"op": "move_above", "args": {"dest_id": "target area", "h": 0.01, "obj": "small beaker"}}
    door = to_primitives(
        "Keep the gripper closed on the door handle and move the robotic arm forward until the door is fully closed.",
        SCENE,
    )
    assert door[1]["args"] == {"direction": "forward", "dist": 0.4, "until": "door_closed"}
    assert to_primitives(
        "Pause current execution, return to perform the omitted grasp, then resume the remaining workflow.", SCENE
    )[1]["args"] == {"pose_id": "omitted:grasp"}
    g3 = to_primitives(
        "Keep the gripper closed to secure the Erlenmeyer flask and move the robotic arm to its "
        "original position while maintaining orientation horizontal.",
        SCENE,
    )
    assert g3[1]["args"] == {"dest_id": "its original position", "h": 0.01, "obj": "Erlenmeyer flask"}
    assert format_primitive(g3[0]) == "gripper_close()"


@pytest.mark.parametrize(
    "text, want",
    [
        (
            "Release the gripper, re-align the arm to center the small beaker, then grip it firmly.",
            ["gripper_open", "align_to", "gripper_close"],
        ),
        (
            "Hold the arm still, keep the gripper state unchanged and keep the gripper level.",
            ["hold_position", "hold_gripper", "set_orient"],
        ),
        (
            "Grab the beaker, carry it to the target area and release it.",  # two beakers in the scene: ambiguous
            ["manual", "move_above", "gripper_open"],
        ),
        (
            "Grab the flask, carry it to the target area and release it.",
            ["gripper_open", "align_to", "gripper_close", "move_above", "gripper_open"],
        ),
        ("Lower the arm by 2 cm", ["delta_pos"]),
        ("Move the arm side to side until the liquid is well mixed.", ["oscillate"]),
        ("Gradually tilt the flask until it is completely poured out.", ["tilt_pour"]),
    ],
)
def test_paraphrases_map(text, want):
    assert ops(text) == want


def test_unmappable_text_becomes_manual_with_the_phrase_never_a_guess():
    p = to_primitives("Wipe the bench with a cloth.", SCENE)
    assert p == [{"op": "manual", "args": {"phrase": "wipe bench with cloth"}}]
    p = to_primitives("Grasp the pipette and lift it.", SCENE)  # not an object of this scene
    assert p[0] == {"op": "manual", "args": {"phrase": "grasp pipette"}} and p[1]["op"] == "delta_pos"
    assert not executable(p)
    assert to_primitives(NO_CORRECTION, SCENE) == [] and to_primitives("", SCENE) == []
    assert to_primitives(STRATEGIES["MANUAL"][1], SCENE)[0]["op"] == "manual"


def test_clause_splitting_keeps_purposes_out_of_actions():
    assert clauses("Keep the arm horizontal to complete the experiment safely.") == [
        "keep arm horizontal",
        "to complete experiment safely",
    ]
