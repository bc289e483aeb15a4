"""PyBullet physics presets (backend_kwargs.physics): what each sets, old runs resume as `reference` only, bad names
are one line, and the label check of scripts/check_physics.py tells a changed make-up from the same one."""

import json
import sys

import pybullet as p
import pytest
from conftest import gen

from scripts.check_physics import compare
from sim_backends import make_backend
from sim_backends.failure_generator import run_nominal
from sim_backends.pybullet.backend import PHYSICS


def test_each_preset_sets_its_solver_and_changes_the_episode():
    traces = {}
    for name in ("reference", "fast", "reference"):
        src = make_backend("pybullet", render=False, physics=name)
        try:
            ep = run_nominal(src, "pick_place_beaker_large", 3, "seen")
            params = p.getPhysicsEngineParameters(physicsClientId=src.cid)
            assert params["numSolverIterations"] == PHYSICS[name].solver_iterations
            spin = p.getDynamicsInfo(src.scene.robot.id, 9, physicsClientId=src.cid)[7]  # a finger's spinning friction
            assert (spin > 0) == PHYSICS[name].torsional_friction
            traces.setdefault(name, []).append(json.dumps(ep.state_trace, sort_keys=True))
        finally:
            src.close()
    assert traces["reference"][0] == traces["reference"][1]  # the same seed, the same episode
    assert traces["fast"][0] != traces["reference"][0]  # the preset reaches the physics


def test_an_unknown_preset_is_one_line(tmp_path):
    r = gen(tmp_path / "o", "num_episodes=0", "preset=demo", "backend_kwargs.physics=quick", check=False)
    assert r.returncode == 2 and "Traceback" not in r.stderr and r.stderr.strip().count("\n") == 0
    assert "physics" in r.stderr and "reference" in r.stderr


def test_a_run_written_before_the_key_resumes_as_reference_only(tmp_path):
    """A run.json without `physics` was made with `reference`: it resumes under that preset and is refused in one
    line under another, which would mix two physics in one dataset."""
    out = tmp_path / "o"
    gen(out, "num_episodes=0", "preset=demo", "backend_kwargs.physics=reference")
    run = json.loads((out / "run.json").read_text())
    del run["backend_kwargs"]["physics"]
    (out / "run.json").write_text(json.dumps(run))
    before = (out / "run.json").read_bytes()
    gen(out, "num_episodes=0", "preset=demo", "backend_kwargs.physics=reference")
    r = gen(out, "num_episodes=0", "preset=demo", "backend_kwargs.physics=fast", check=False)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "backend_kwargs" in r.stderr
    assert (out / "run.json").read_bytes() == before


@pytest.mark.parametrize("written_with_section", [True, False])
def test_an_old_run_reads_as_reference_whatever_the_default(monkeypatch, written_with_section):
    """Should the default change, an old run.json (with a backend_kwargs section but no `physics`, or from before
    the section existed) still reads as the preset it was made with, not as the new default."""
    import sim_backends.generate as g

    monkeypatch.setattr(g, "_default_backend_kwargs", lambda: {"wrist": False, "physics": "fast"})
    new = {"backend_kwargs": {"wrist": False, "physics": "fast"}, "backend_files": {}}
    old = {"backend_kwargs": {"wrist": False}} if written_with_section else {"wrist": False}
    assert g._upgrade_identity(old, new)["backend_kwargs"]["physics"] == "reference"


def _rows(nominal_failed: int, types: list[str]) -> list[dict]:
    rows = []
    for j, t in enumerate(types):
        ok = j >= nominal_failed
        rows.append(
            {
                "pair": j,
                "scenario": "s",
                "role": "nominal",
                "outcome": "success" if ok else "explained",
                "failure_type": None if ok else "object_slippage",
                "category": None if ok else 2,
                "severity": None if ok else 2,
            }
        )
        rows.append(
            {
                "pair": j,
                "scenario": "s",
                "role": "injected",
                "outcome": "explained",
                "failure_type": t,
                "category": 1,
                "severity": 2,
            }
        )
    return rows


@pytest.mark.parametrize(
    "b_failed, b_types, keeps",
    [
        (0, None, True),  # the same labels
        (20, None, False),  # a fifth of the nominal runs fail
        (0, ["step_omission"] * 60, False),  # another failure type throughout
    ],
)
def test_the_label_check_tells_a_changed_make_up(b_failed, b_types, keeps):
    types = ["step_omission", "object_slippage", "sequence_reversal"] * 20
    res = compare(_rows(0, types), _rows(b_failed, b_types or types))
    assert res["keeps_labels"] is keeps
    assert (res["paired_agreement"] == 1.0 and not res["changed"]) if keeps else res["changed"]
    assert res["nominal_success_paired"]["lost"] == b_failed


def test_the_label_check_reads_a_one_sided_loss_in_pairs_and_refuses_unpaired_runs():
    """Six nominal runs lost and none won (2 -> 8 failed of 201) is within an unpaired test's noise, not a paired
    test's."""
    types = ["step_omission", "object_slippage", "sequence_reversal"] * 67
    res = compare(_rows(2, types), _rows(8, types))
    assert res["tests"]["nominal_success"]["p"] >= 0.05 and res["nominal_success_paired"]["p"] < 0.05
    with pytest.raises(ValueError, match="same episodes"):
        compare(_rows(0, types), _rows(0, types)[2:] + _rows(0, types)[:2])


@pytest.mark.parametrize(
    "args, says", [(["a=fast", "b=fast"], "same preset"), (["variant=test_both"], "sealed"), (["b=quick"], "quick")]
)
def test_the_check_refuses_bad_settings_in_one_line(args, says):
    from conftest import ROOT, run

    r = run([sys.executable, str(ROOT / "scripts/check_physics.py"), *args])
    assert r.returncode == 2 and "Traceback" not in r.stderr and r.stderr.strip().count("\n") == 0
    assert says in r.stderr


def test_the_generator_and_the_backend_default_to_the_same_preset():
    from sim_backends.generate import _default_backend_kwargs
    from sim_backends.pybullet.backend import DEFAULT_PHYSICS

    assert _default_backend_kwargs()["physics"] == DEFAULT_PHYSICS


def test_a_step_adding_episodes_to_a_run_of_another_preset_is_refused_in_one_line(tmp_path):
    """make reproduce's later steps (reproduce-more, a validation lever, a tuned row's new pairs) check the preset of
    the run's seen episodes first: REPRO_PHYSICS moved to prefix on 6 Dec, and an older run's folder holds
    reference episodes (a run.json without the key reads as reference)."""
    from labrobfail_vlm.config import ConfigError
    from sim_backends.generate import check_same_physics, run_physics

    seen = tmp_path / "seen"
    check_same_physics(str(seen), "backend_kwargs.physics=prefix", "reproduce-more")  # nothing generated yet
    seen.mkdir()
    (seen / "run.json").write_text(json.dumps({"backend": "pybullet", "backend_kwargs": {"wrist": True}}))
    assert run_physics(seen) == "reference"
    (seen / "run.json").write_text(json.dumps({"backend": "pybullet"}))  # written before backend_kwargs existed
    assert run_physics(seen) == "reference"
    check_same_physics(str(seen), "backend_kwargs.physics=reference", "reproduce-more")
    with pytest.raises(ConfigError, match=r"^REPRO_PHYSICS: reproduce-more would simulate with physics=prefix, but"):
        check_same_physics(str(seen), "backend_kwargs.physics=prefix", "reproduce-more")
    (seen / "run.json").write_text(json.dumps({"backend": "maniskill", "backend_kwargs": {}}))
    assert run_physics(seen) is None  # no PyBullet preset to compare
    (seen / "run.json").write_text("{")
    with pytest.raises(ConfigError, match="not valid JSON"):
        run_physics(seen)
