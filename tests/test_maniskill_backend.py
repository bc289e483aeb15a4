"""Real ManiSkill3/SAPIEN episodes: stock and lab-bench scenarios, labels from state, explicit undo of
physics perturbations, same seed same episode, offline refusal. (The stepping contract itself runs
over this backend in test_backend_contract.py.)"""

import numpy as np
import pytest

from sim_backends.maniskill import vulkan_problem

_why = vulkan_problem()
if _why:  # only where no Vulkan device can exist; the reason shows in the summary (pytest -rs)
    pytest.skip(f"maniskill: {_why}", allow_module_level=True)

from sim_backends import make_backend  # noqa: E402
from sim_backends.failure_generator import run_pair  # noqa: E402
from sim_backends.perturbations import control  # noqa: E402
from sim_backends.perturbations.physics import PhysicsEvent  # noqa: E402

pytestmark = pytest.mark.maniskill

SIZE = 32


@pytest.fixture(scope="module")
def src():
    s = make_backend("maniskill", image_size=SIZE)
    yield s
    s.close()


def _run(src, scenario, seed, perturb=None, events=()):
    src.reset(scenario, seed)
    kfs = src.scripted_keyframes()
    if perturb is not None:
        kfs = perturb(kfs)
    return src.execute(kfs, events)


def test_stock_task_nominal_and_gripper_fault(src):
    ok = _run(src, "pick_cube", 1)
    assert ok.labels.success and ok.task_meta.objects["obj"].kind == "vessel"
    assert ok.state_trace["rate_hz"] == 20.0 and ok.camera_names == ["front", "side"]
    bad = _run(
        src,
        "pick_cube",
        1,
        lambda k: control.corrupt_gripper(k, ["s0_close", "s0_lift"], 1.0, np.random.default_rng(0))[0],
    )
    assert bad.labels.failure_type == "gripper_control_failure"
    close_i = [k.name for k in bad.executed_keyframes].index("s0_close")
    assert (
        bad.labels.failure_keyframe == close_i and bad.state_trace["width"][bad.state_trace["kf_end"][close_i]] > 0.07
    )


def test_lab_button_pressed_or_missed(src):
    ok = _run(src, "press_button_red", 2)
    assert ok.labels.success and max(ok.state_trace["button.q"]) > 0.007
    miss = _run(
        src,
        "press_button_red",
        2,
        lambda k: control.translate(k, ["s0_touch", "s0_press"], [0.0, 0.06, 0.0], np.random.default_rng(1), 0.05)[0],
    )
    assert miss.labels.failure_type == "operation_position_error" and max(miss.state_trace["button.q"]) < 0.003


def test_physics_perturbation_is_undone_and_seeds_repeat(src):
    """A friction drop during the carry lets the beaker slip; the next episode of the same seed is the
    nominal one again, bit for bit (values set through the SAPIEN API outlive env.reset())."""
    import sapien.physx as physx

    default = physx.get_default_material()
    before = (default.static_friction, default.dynamic_friction)
    ref = _run(src, "pick_place_beaker_small", 4)
    src.reset("pick_place_beaker_small", 4)
    kfs = src.scripted_keyframes()
    at = [k.name for k in kfs].index("s1_carry")
    slip = src.execute(kfs, [PhysicsEvent("grip_force", "robot", 0.005, at), PhysicsEvent("friction", "obj", 0.05, at)])
    assert slip.labels.failure_type == "object_slippage"
    assert (default.static_friction, default.dynamic_friction) == before
    again = _run(src, "pick_place_beaker_small", 4)
    assert again.state_trace == ref.state_trace and again.images == ref.images and again.labels == ref.labels


def test_the_sealed_splits_are_refused_in_one_line(src):
    """Only the PyBullet backend defines the sealed catalogue and scene family."""
    with pytest.raises(ValueError, match="variant: test_both needs the sealed catalogue, which only the pybullet"):
        src.reset("push_cube", 11, "test_both")


def test_pair_from_one_initial_state(src):
    nominal, injected = run_pair(src, "push_cube", 11, "val_both")
    assert nominal.state_trace["obj.pos"][0] == injected.state_trace["obj.pos"][0]
    assert nominal.labels.success and not injected.labels.success
    assert injected.perturbation["level"] == "control"


def test_offline_refusal_and_options(tmp_path):
    cfg = tmp_path / "tasks.yaml"
    cfg.write_text("templates: {}\nscenarios:\n  ycb: {env: PickSingleYCB-v1, template: pick_place}\n")
    with pytest.raises(ValueError, match="PickSingleYCB-v1 needs assets") as e:
        make_backend("maniskill", tasks_file=str(cfg))
    assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="cameras"):
        make_backend("maniskill", cameras=["top"])
    import torch

    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="sim_backend: gpu needs a CUDA device"):
            make_backend("maniskill", sim_backend="gpu")


def test_wrist_view():
    s = make_backend("maniskill", image_size=SIZE, wrist=True, cameras=["front"])
    try:
        s.reset("press_button_red", 0)
        s.begin()
        s.step(s.scripted_keyframes()[0])
        obs = s.observe()
        assert list(obs.images) == ["front", "wrist"]
        assert all(im.shape == (SIZE, SIZE, 3) for im in obs.images.values())
        assert obs.images["wrist"].std() > 0  # it sees something, not a blank frame
    finally:
        s.close()


def test_manifest_counts_physics_signs_and_gripper_faults_both_ways(src):
    """The same forced draws as the PyBullet test, on ManiSkill's pick-and-place: friction and mass of the held
    object and the grip force on both signs, gripper faults both ways, labelled from state."""
    from conftest import SIGNS_AND_FAULTS, check_injection_summary, injected_rows

    check_injection_summary(injected_rows(src, "pick_cube", SIGNS_AND_FAULTS))
