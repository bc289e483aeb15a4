"""The FailureSource stepping contract, run over every registered backend, and the registry's checks."""

import io
import json

import numpy as np
import pytest
from PIL import Image

from sim_backends import available_backends, make_backend
from sim_backends.labeler import REACH, derive_labels
from sim_backends.perturbations import control
from sim_backends.registry import backend_spec, register_backend, register_task, task_templates
from sim_backends.schema import MOVABLE, TRACE_COLUMNS, TaskMeta, check_trace
from sim_backends.source import FailureSource

SIZE = 48
PREFERRED = "press_button_red"  # short (4 keyframes) where a backend has it


@pytest.fixture(scope="module", params=available_backends())
def src(request):
    why = backend_spec(request.param).cls.unavailable()
    if why:  # only a machine that cannot run the backend at all (no device) skips it
        pytest.skip(f"{request.param}: {why}")
    s = make_backend(request.param, image_size=SIZE)
    yield s
    s.close()


def _scenario(src) -> str:
    names = src.scenarios()
    return PREFERRED if PREFERRED in names else names[0]


def _run(src, seed=3, perturb=None):
    src.reset(_scenario(src), seed, "seen")
    kfs = src.scripted_keyframes()
    if perturb is not None:
        kfs = perturb(kfs)
    return src.execute(kfs)


def test_reset_is_deterministic(src):
    a, b = _run(src), _run(src)
    assert a.state_trace == b.state_trace and a.images == b.images and a.labels == b.labels
    assert a.task_meta.to_dict() == b.task_meta.to_dict()
    c = _run(src, seed=4)
    assert c.state_trace["t"][0] == 0.0 and c.state_trace != a.state_trace  # another seed, another scene


def test_trace_schema_and_images_per_view(src):
    ep = _run(src)
    tr = ep.state_trace
    assert check_trace(tr, ep.task_meta) == []
    assert tr["rate_hz"] > 0 and all(c in tr for c in TRACE_COLUMNS)
    assert len(tr["kf_end"]) == len(ep.executed_keyframes) == len(ep.task_meta.executed)
    assert len(ep.images) == len(ep.camera_names) >= 1
    # the arm's base is recorded, and the hand and every object the plan moves start within the labeler's REACH of it
    base = ep.task_meta.robot_base
    assert base is not None and len(base) == 3
    starts = [tr["ee_pos"][0]] + [tr[f"{m}.pos"][0] for m, o in ep.task_meta.objects.items() if o.kind in MOVABLE]
    assert all(np.hypot(p[0] - base[0], p[1] - base[1]) < REACH for p in starts)
    for view in ep.images:
        assert len(view) == len(ep.executed_keyframes)
        assert Image.open(io.BytesIO(view[0])).size == (SIZE, SIZE)


@pytest.mark.parametrize("perturbed", [False, True])
def test_labels_rederived_from_stored_trace(src, perturbed):
    cut = (lambda k: control.truncate(k, [k[1].name], np.random.default_rng(0))[0]) if perturbed else None
    ep = _run(src, perturb=cut)
    assert ep.labels.success != perturbed
    meta = TaskMeta.from_json(ep.task_meta.to_json())  # what a shard stores
    assert meta == ep.task_meta
    trace = json.loads(json.dumps(ep.state_trace))
    assert derive_labels(trace, meta) == derive_labels(trace, meta.to_dict()) == ep.labels


def test_stepping_by_hand_equals_execute(src):
    ref = _run(src)
    src.reset(_scenario(src), 3, "seen")
    kfs = src.scripted_keyframes()
    src.begin()
    start = src.observe()
    assert start.keyframe == 0 and set(start.images) == set(src.camera_names)
    for i, kf in enumerate(kfs):
        src.step(kf)
        obs = src.observe()
        assert obs.keyframe == i + 1 and len(obs.state["ee_pos"]) == 3
        assert all(im.shape == (SIZE, SIZE, 3) and im.dtype == np.uint8 for im in obs.images.values())
        so_far = src.trace_so_far()
        assert len(so_far["kf_end"]) == i + 1 and so_far["rate_hz"] == ref.state_trace["rate_hz"]
        assert obs.state["t"] == so_far["t"][-1]
    ep = src.finish()
    assert ep.state_trace == ref.state_trace and ep.images == ref.images and ep.labels == ref.labels
    with pytest.raises(RuntimeError, match="reset"):
        src.step(kfs[0])  # the episode is finished
    with pytest.raises(RuntimeError, match="fresh reset"):
        src.begin()


def test_correction_steps_from_the_current_state(src):
    """A supervisor's correction is more keyframes from wherever the arm is: no reset in between."""
    src.reset(_scenario(src), 3, "seen")
    kfs = src.scripted_keyframes()
    src.begin()
    for kf in kfs[:2]:
        src.step(kf)
    before = src.observe().state["ee_pos"]
    src.step(kfs[0])  # back to the first keyframe, from the second
    for kf in kfs[1:]:
        src.step(kf)
    ep = src.finish()
    assert len(ep.executed_keyframes) == len(ep.state_trace["kf_end"]) == len(kfs) + 2
    assert ep.state_trace["ee_pos"][ep.state_trace["kf_end"][1]] == before


def test_registry_checks_its_promises():
    with pytest.raises(ValueError, match="not a FailureSource subclass"):
        register_backend("bogus")(dict)
    with pytest.raises(ValueError, match="JSON-serialisable"):
        register_backend("bogus2", fn=print)
    taken = backend_spec(available_backends()[0]).name  # imports it, so it is registered
    with pytest.raises(ValueError, match="already registered"):
        register_backend(taken)(type("Other", (FailureSource,), {}))
    assert "bogus" not in available_backends()

    @register_task("pick_place", backend="other_sim")
    def other(plan, params):  # the same template name under another backend is a different template
        pass

    assert task_templates("other_sim")["pick_place"].cls is other
    assert task_templates("pybullet")["pick_place"].cls is not other
