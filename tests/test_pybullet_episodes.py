"""Real PyBullet episodes: nominal success, labels from state for injected failures, determinism."""

import numpy as np
import pytest

from sim_backends import make_backend
from sim_backends.labeler import derive_labels, irreversible_sample
from sim_backends.perturbations import control


@pytest.fixture(scope="module")
def src():
    s = make_backend("pybullet", image_size=64)
    yield s
    s.close()


def _run(src, scenario, seed, perturb=None):
    src.reset(scenario, seed)
    kfs = src.scripted_keyframes()
    if perturb:
        kfs, _ = perturb(kfs)
    return src.execute(kfs)


def test_press_button_nominal_and_truncated(src):
    ok = _run(src, "press_button_red", 3)
    assert ok.labels.success and max(ok.state_trace["button.q"]) > 0.007
    rng = np.random.default_rng(0)
    bad = _run(src, "press_button_red", 3, lambda k: control.truncate(k, ["s0_touch"], rng))
    assert not bad.labels.success
    assert bad.labels.failure_type == "incomplete_trajectory" and bad.labels.category == 3
    assert max(bad.state_trace["button.q"]) < 0.002  # the button never moved
    assert len(bad.images[0]) == len(ok.images[0]) == 4 and ok.images[0][0][:4] == b"\x89PNG"


def test_gripper_fault_is_seen_in_the_fingers(src):
    rng = np.random.default_rng(0)
    ep = _run(src, "pick_place_bottle", 1, lambda k: control.corrupt_gripper(k, ["s0_close", "s0_lift"], 1.0, rng))
    assert ep.labels.failure_type == "gripper_control_failure"
    close_i = [k.name for k in ep.executed_keyframes].index("s0_close")
    assert ep.labels.failure_keyframe == close_i
    assert ep.state_trace["width"][ep.state_trace["kf_end"][close_i]] > 0.07
    # Re-deriving from the recorded trace alone gives the same labels.
    assert derive_labels(ep.state_trace, ep.task_meta) == ep.labels


def test_gripper_opening_mid_carry_drops_and_breaks_the_glass(src):
    """Opening the fingers while carrying: a gripper control failure (the object was let go, not lost), and
    the fall from carry height is fast enough to count as broken glassware (Fatal)."""
    rng = np.random.default_rng(0)
    ep = _run(src, "pick_place_bottle", 1, lambda k: control.corrupt_gripper(k, ["s1_carry"], 1.0, rng))
    assert ep.labels.failure_type == "gripper_control_failure", ep.labels.evidence
    assert "opened while carrying" in ep.labels.evidence and ep.labels.severity == 3  # Fatal


def test_same_seed_same_episode(src):
    a = _run(src, "open_oven_center", 5)
    b = _run(src, "open_oven_center", 5)
    assert a.state_trace == b.state_trace and a.images == b.images and a.labels.success
    c = _run(src, "open_oven_center", 6)
    assert c.state_trace["ee_pos"] != a.state_trace["ee_pos"]


def test_unknown_scenario_and_variant(src):
    with pytest.raises(ValueError, match="unknown scenario"):
        src.reset("fly_to_moon", 0)
    with pytest.raises(ValueError, match="unknown variant"):
        src.reset("press_button_red", 0, "unseen_planet")


def test_logic_failures_from_step_order(src):
    from sim_backends.perturbations import semantic

    om = _run(src, "pick_place_bottle", 1, lambda k: semantic.omit(k, 0))
    assert om.labels.failure_type == "step_omission" and om.labels.failure_keyframe == 0
    rev = _run(src, "stir_beaker", 1, lambda k: semantic.permute(k, 0, 2))
    assert rev.labels.failure_type == "sequence_reversal" and rev.labels.category == 4
    assert rev.labels.failure_keyframe == 0  # it stirred before it had the rod


def _shifted(kfs, names, dy):
    import dataclasses

    return [dataclasses.replace(k, pos=(k.pos[0], k.pos[1] + dy, k.pos[2])) if k.name in names else k for k in kfs], {}


def test_a_pick_that_ends_holding_is_watched_to_the_end(src):
    """The pick template ends on its lift: fingers that open there drop the vessel (no release step follows to
    end the watch early), and an off-centre reach that pushes the vessel aside closes the fingers on nothing
    (a misaligned grasp, not a slip: the vessel never left the bench)."""
    rng = np.random.default_rng(0)
    ok = _run(src, "pick_bottle", 1)
    assert ok.labels.success
    dropped = _run(src, "pick_bottle", 1, lambda k: control.corrupt_gripper(k, ["s0_lift"], 1.0, rng))
    assert dropped.labels.failure_type == "gripper_control_failure", dropped.labels.evidence
    assert "opened while carrying" in dropped.labels.evidence
    pushed = _run(src, "pick_bottle", 1, lambda k: _shifted(k, {"s0_reach", "s0_close"}, 0.032))
    assert pushed.labels.failure_type == "grasp_target_misalignment", pushed.labels.evidence
    assert "closed on nothing" in pushed.labels.evidence and max(p[2] for p in pushed.state_trace["obj.pos"]) < 0.02


def test_randomised_scene_family_widens_seen_benches_only():
    """The tower's domain randomisation (scene_family=randomised) draws seen benches of any brightness with textures
    no split uses; a held-out-scene episode keeps its own family, and the same seed gives the same bench."""
    from sim_backends.pybullet import scene

    seen = [scene.draw_appearance("seen", np.random.default_rng(i), "randomised") for i in range(200)]
    value = [max(a["bench"][:3]) for a in seen]
    lo, hi = scene.SCENE_FAMILIES["seen"]["bench_value"]
    assert min(value) < lo and max(value) > hi  # beyond the seen family's range on both sides
    kinds = {a["texture"] for a in seen}
    assert {"stripes", "blotches"} <= kinds and not kinds & set(scene.SCENE_FAMILIES["val"]["textures"])
    for held in ("val_both", "test_scene"):
        assert scene.draw_appearance(held, np.random.default_rng(0), "randomised") == scene.draw_appearance(
            held, np.random.default_rng(0)
        )
    assert seen[3] == scene.draw_appearance("seen", np.random.default_rng(3), "randomised")
    with pytest.raises(ValueError, match="scene_family: unknown family 'moon'"):
        scene.scene_family("seen", "moon")
    for held in ("val", "sealed"):  # never the held-out benches under a seen label
        with pytest.raises(ValueError, match=f"scene_family: {held} is the {held} splits' own family"):
            scene.scene_family("seen", held)
    src = make_backend("pybullet", image_size=32, cameras=["front"], max_distractors=0, scene_family="randomised")
    try:
        src.reset("press_button_red", 4)
        assert src.scene.appearance == scene.draw_appearance("seen", np.random.default_rng(4), "randomised")
        assert src.execute(src.scripted_keyframes()).labels.success  # a dark striped bench changes no physics
    finally:
        src.close()


def test_randomised_object_colours_recolour_seen_glassware_only_and_change_no_physics():
    """object_colours=randomised (the tower's pretraining data) draws each seen-catalogue vessel, rod and distractor a
    colour up to saturation 0.8, every part of a compound alike, from its own random numbers: the same initial state,
    trace and labels as without it, other pictures; held-out catalogues keep their colours."""
    import colorsys

    import pybullet as pb

    from sim_backends.pybullet import scene

    def colours(src) -> dict[int, set[tuple[float, ...]]]:
        return {
            b: {tuple(round(c, 3) for c in d[7]) for d in pb.getVisualShapeData(b, physicsClientId=src.cid)}
            for b in scene.glassware_bodies(src.scene)
        }

    kw = {"image_size": 48, "cameras": ["front"], "max_distractors": 3}
    on, off = make_backend("pybullet", object_colours="randomised", **kw), make_backend("pybullet", **kw)
    try:
        for variant in ("seen", "val_object", "test_both"):
            on.reset("pick_place_beaker_large", 11, variant)
            off.reset("pick_place_beaker_large", 11, variant)
            a, b = colours(on), colours(off)
            assert a.keys() == b.keys() and len(a) >= 2
            if variant != "seen":
                assert a == b  # a held-out catalogue keeps its own colours
                continue
            assert all(len(c) == 1 for c in a.values()) and all(a[k] != b[k] for k in a)
            sat = [colorsys.rgb_to_hsv(*next(iter(c))[:3])[1] for c in a.values()]
            assert max(sat) <= scene.OBJECT_COLOURS["randomised"]["sat"][1] + 1e-3
            ea, eb = on.execute(on.scripted_keyframes()), off.execute(off.scripted_keyframes())
            assert ea.state_trace == eb.state_trace and ea.labels == eb.labels and ea.images != eb.images
    finally:
        on.close()
        off.close()


def test_the_lowpoly_robot_file_is_one_file_shared_by_every_process():
    """Each process once wrote its own temp folder and left it behind (a thousand after a day of runs)."""
    import subprocess
    import sys
    from pathlib import Path

    code = "from sim_backends.pybullet.robot import lowpoly_urdf; print(lowpoly_urdf())"
    paths = {
        subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
        for _ in range(2)
    }
    assert len(paths) == 1
    urdf = Path(paths.pop())
    assert urdf.is_file() and "meshes/collision/" in urdf.read_text() and "package://" not in urdf.read_text()
    assert not list(urdf.parent.glob(urdf.name + "*.tmp"))


def test_button_lamp_lights_on_a_press_and_not_on_a_press_beside_the_button(tmp_path):
    """`button_lamp=true`: the housing renders lit in exactly the keyframes by which the pressed goal holds on the trace
    (a grid then shows the press); dark for a press 7 cm beside the button and for a shallow one (3 mm of travel);
    off, the same episode records the same trace and the frames before the press are the same bytes."""
    import dataclasses
    import io

    import pybullet as p
    from PIL import Image

    from labrobfail_vlm.config import ConfigError
    from sim_backends import generate
    from sim_backends.plan_builder import PRESSED_MIN_TRAVEL
    from sim_backends.pybullet.assets import HOUSING_RGBA, LAMP_RGBA

    def lit(ep) -> list[bool]:  # per front keyframe: magenta lamp pixels present
        out = []
        for png in ep.images[0]:
            a = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
            out.append(int(((a[..., 0] > 170) & (a[..., 1] < 110) & (a[..., 2] > 140)).sum()) >= 10)
        return out

    def pressed_by(ep) -> list[bool]:  # per keyframe: the pressed goal holds on the trace up to its end
        q, ends = ep.state_trace["button.q"], ep.state_trace["kf_end"]
        return [max(q[: e + 1]) >= PRESSED_MIN_TRAVEL for e in ends]

    beside = lambda k: _shifted(k, ["s0_touch", "s0_press"], 0.07)  # noqa: E731

    def shallow(k):  # the press stops 19 mm higher: about 3 mm of travel
        return [
            dataclasses.replace(x, pos=(*x.pos[:2], x.pos[2] + 0.019)) if x.name == "s0_press" else x for x in k
        ], {}

    lamp = make_backend("pybullet", image_size=128, cameras=["front"], max_distractors=0, button_lamp=True)
    plain = make_backend("pybullet", image_size=128, cameras=["front"], max_distractors=0)
    try:
        housing = lambda s: p.getVisualShapeData(s.scene.objects["button"].body, physicsClientId=s.cid)[0][7]  # noqa: E731
        ok = _run(lamp, "press_button_red", 3)
        assert ok.labels.success and housing(lamp) == pytest.approx(LAMP_RGBA)
        shown = lit(ok)
        assert shown == pressed_by(ok) and shown[0] is False and shown[-1] is True
        for perturb, travel in ((beside, (0.0, 0.001)), (shallow, (0.001, PRESSED_MIN_TRAVEL))):
            miss = _run(lamp, "press_button_red", 3, perturb)
            assert travel[0] <= max(miss.state_trace["button.q"]) < travel[1]  # none, then some but short of a press
            assert miss.labels.failure_type == "operation_position_error", miss.labels.evidence
            assert housing(lamp) == pytest.approx(HOUSING_RGBA) and not any(lit(miss))
        same = _run(plain, "press_button_red", 3)
        assert (
            same.state_trace == ok.state_trace and housing(plain) == pytest.approx(HOUSING_RGBA) and not any(lit(same))
        )
        assert same.images[0][0] == ok.images[0][0] and same.images[0][-1] != ok.images[0][-1]
    finally:
        lamp.close()
        plain.close()
    with pytest.raises(ValueError, match="button_lamp: expected true or false"):
        make_backend("pybullet", render=False, button_lamp="yes")
    out = tmp_path / "gen"  # the generator refuses it in one line before it writes anything
    with pytest.raises(ConfigError, match=r"^backend_kwargs.button_lamp: expected true or false, got 'maybe'$"):
        generate.validate(
            generate.load_config(["backend=pybullet", "backend_kwargs.button_lamp=maybe", f"out_dir={out}"])
        )
    assert not out.exists()


def test_broken_glass_renders_shards_once_a_dropped_bottle_has_landed():
    """`broken_glass=true`: a bottle let go mid-carry (an impact the labeler calls breakage, Fatal) is drawn as shards
    on the bench in every keyframe rendered once it has come to rest, the whole bottle hidden; the trace and labels
    are those of the same episode with the option off, and so are the images before the failure's keyframe; the
    layered renderer draws the shards as the whole scene does. A grasp that never closes breaks nothing: every image
    the same bytes. A bottle that breaks in the settling after the last keyframe is drawn broken in that keyframe,
    the one its label names."""
    import dataclasses

    import pybullet as p

    from labrobfail_vlm.config import ConfigError
    from sim_backends import generate
    from sim_backends.pybullet.assets import BENCH_TOP
    from sim_backends.robot_signals import frame_times, irreversible
    from sim_backends.schema import check_trace, trace_until

    kw = {"image_size": 64, "cameras": ["front"], "max_distractors": 0}
    on = make_backend("pybullet", broken_glass=True, **kw)
    off = make_backend("pybullet", **kw)
    whole = make_backend("pybullet", broken_glass=True, layered_render=False, **kw)
    try:

        def episode(src, names):
            rng = np.random.default_rng(0)
            return _run(src, "pick_place_bottle", 1, lambda k: control.corrupt_gripper(k, names, 1.0, rng))

        def alpha(src) -> float:
            return p.getVisualShapeData(src.scene.objects["obj"].body, physicsClientId=src.cid)[0][7][3]

        broken, plain = episode(on, ["s1_carry"]), episode(off, ["s1_carry"])
        assert broken.labels == plain.labels and broken.labels.severity == 3  # Fatal
        assert broken.state_trace == plain.state_trace
        shown = [a != b for a, b in zip(broken.images[0], plain.images[0])]
        first, k = shown.index(True), broken.labels.failure_keyframe
        assert first >= k and all(shown[first:]) and len(shown) - first >= 2, (k, shown)
        assert alpha(on) == 0.0 and alpha(off) == 1.0
        n = p.getNumBodies(physicsClientId=on.cid)
        assert n == p.getNumBodies(physicsClientId=off.cid) + 1  # the shards, drawn on the bench (not in the air)
        shards = p.getBodyUniqueId(n - 1, physicsClientId=on.cid)
        assert abs(p.getBasePositionAndOrientation(shards, physicsClientId=on.cid)[0][2] - BENCH_TOP) < 0.003
        assert len(p.getVisualShapeData(shards, physicsClientId=on.cid)) == 10
        assert episode(whole, ["s1_carry"]).images == broken.images  # layered = whole scene, shards included
        fault, same = episode(on, ["s0_close"]), episode(off, ["s0_close"])
        assert fault.labels.severity != 3 and fault.images == same.images and alpha(on) == 1.0

        def let_go_last(src):  # the plan ends by opening the hand at carry height: the bottle falls in the settling
            src.reset("pick_place_bottle", 1)
            kfs = src.scripted_keyframes()
            i, release = [k.name for k in kfs].index("s1_carry"), next(k for k in kfs if k.name == "s1_release")
            return src.execute([*kfs[: i + 1], dataclasses.replace(release, pos=kfs[i].pos, settle_steps=10)])

        late, before = let_go_last(on), let_go_last(off)
        end = late.state_trace["kf_end"][-1]
        assert late.labels == before.labels and late.labels.severity == 3  # Fatal at the last keyframe
        assert late.labels.failure_keyframe == len(late.images[0]) - 1
        assert irreversible_sample(late.state_trace, late.task_meta)[0] > end  # it breaks after that keyframe's end
        assert late.images[0][:-1] == before.images[0][:-1] and late.images[0][-1] != before.images[0][-1]
        assert alpha(on) == 0.0  # drawn again at the settled state, the bottle hidden and its shards shown
        tr = late.state_trace  # the frame's state and time are read where its images show it
        assert tr["images_at"] == [*tr["kf_end"][:-1], len(tr["t"]) - 1] and "images_at" not in before.state_trace
        assert check_trace(tr, late.task_meta) == [] and "images_at" not in trace_until(tr, len(tr["kf_end"]) - 1)
        picks = list(range(len(tr["kf_end"])))
        assert frame_times(tr, picks)[:-1] == frame_times(before.state_trace, picks)[:-1]
        broke_s = irreversible(tr, late.task_meta.to_dict())["irreversible_s"]
        assert frame_times(before.state_trace, picks)[-1] < broke_s < frame_times(tr, picks)[-1]  # shown after it
        # At the episode's end a piece still moving is drawn if it lies on something, not while in the air
        body = on.scene.objects["obj"].body
        on._broken.clear()  # as if not drawn yet: its trace holds the breaking impact
        p.resetBaseVelocity(body, [0.3, 0.0, 0.0], physicsClientId=on.cid)
        on._break_glass()
        assert not on._broken  # rolling: not at rest during the episode
        on._break_glass(settled=True)
        assert on._broken == {"obj"}  # lying on the bench at the end
        on._broken.clear()
        pos, quat = p.getBasePositionAndOrientation(body, physicsClientId=on.cid)
        p.resetBasePositionAndOrientation(body, (pos[0], pos[1], pos[2] + 0.3), quat, physicsClientId=on.cid)
        p.resetBaseVelocity(body, [0.3, 0.0, 0.0], physicsClientId=on.cid)
        p.performCollisionDetection(physicsClientId=on.cid)
        on._break_glass(settled=True)
        assert not on._broken  # in the air
    finally:
        for src in (on, off, whole):
            src.close()
    with pytest.raises(ConfigError, match=r"^backend_kwargs.broken_glass: expected true or false, got 'maybe'$"):
        generate.validate(generate.load_config(["backend=pybullet", "backend_kwargs.broken_glass=maybe"]))
