"""What the simulator drew into a model's training grids (the lamp, broken glass) travels from the shards' run.json
to the dataset, the checkpoint and labrobfail-supervise, which refuses a world drawn otherwise."""

import json
import shutil

import pytest
from conftest import cli, run_here
from test_train import small_ds, tiny  # noqa: F401  (session fixtures: a built dataset, a tiny Qwen3-VL)

from labrobfail_vlm import drawing
from labrobfail_vlm.config import ConfigError

OFF = {"broken_glass": False, "button_lamp": False}


def test_merge_keeps_what_every_run_agrees_on():
    lit = {"broken_glass": True, "button_lamp": True}
    assert drawing.merge([lit, dict(lit)]) == lit
    assert drawing.merge([lit, OFF]) == {"broken_glass": "mixed", "button_lamp": "mixed"}
    assert drawing.merge([lit, None]) == {"broken_glass": "mixed", "button_lamp": "mixed"}  # one run unknown
    assert drawing.merge([None, None]) is None
    assert drawing.merge([{"broken_glass": True, "button_lamp": False}, lit]) == {
        "broken_glass": True,
        "button_lamp": "mixed",
    }
    assert drawing.mismatches(lit, {"button_lamp": True}) == ["broken_glass=true"]  # absent: the backend's off
    assert drawing.mismatches({"broken_glass": "mixed", "button_lamp": False}, {"broken_glass": True}) == []
    assert drawing.mismatches(None, {"button_lamp": True}) == []


def test_a_dataset_and_its_trained_checkpoint_record_the_drawing(small_ds, tiny, tmp_path):  # noqa: F811
    assert json.loads((small_ds / "stats.json").read_text())["drawing"] == OFF  # run6: generated with defaults
    from labrobfail_vlm.train.checkpoint import trained_drawing

    out = tmp_path / "run"
    quiet = ["global_batch=2", "per_device_batch=2", "wandb.enabled=false", "progress=false", "max_steps=1"]
    argv = ["train.py", "preset=tiny", "tower=scratch", f"model.path={tiny}", f"dataset_dir={small_ds}", *quiet]
    r = run_here([*argv, f"output_dir={out}"])
    assert r.returncode == 0, r.stderr
    assert trained_drawing(out / "final") == OFF
    assert trained_drawing(tiny) is None  # a base model: nothing recorded, nothing checked


@pytest.fixture
def lit_model(tiny, tmp_path):  # noqa: F811
    """The tiny model as a full fine-tuned checkpoint whose manifest says its grids had the lamp lit."""
    out = tmp_path / "lit"
    shutil.copytree(tiny, out)
    man = {"tuning": "full", "grid": None, "drawing": {"broken_glass": "mixed", "button_lamp": True}}
    (out / "labrobfail.json").write_text(json.dumps(man))
    return out


def test_supervise_refuses_a_world_drawn_otherwise(lit_model, tmp_path):
    out = tmp_path / "sup"
    argv = [cli("supervise"), "supervisor=vlm", f"vlm.model={lit_model}", "task=press_button_red", "trials=1"]
    r = run_here([*argv, "image_size=48", "cameras=[front]", "progress=false", f"out_dir={out}"])
    last = r.stderr.strip().splitlines()[-1]  # after the weights' loading bar
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert last == (
        "error: vlm.model: trained on grids drawn with button_lamp=true; set backend_kwargs the same way "
        "(or vlm.check_drawing=false to supervise anyway)"
    )
    assert not (out / "log.jsonl").exists()  # refused before the first trial
    from labrobfail_vlm.analyzer import FailureAnalyzer
    from sim_backends.supervision.vlm import VLMSupervisor

    fa = FailureAnalyzer.from_pretrained(lit_model)
    VLMSupervisor(model=str(lit_model), analyzer=fa).check_drawing({"button_lamp": True, "broken_glass": True})
    with pytest.raises(ConfigError, match="button_lamp=true"):
        VLMSupervisor(model=str(lit_model), analyzer=fa).check_drawing({"broken_glass": True})
    VLMSupervisor(model=str(lit_model), analyzer=fa, check_drawing=False).check_drawing({})
    with pytest.raises(ConfigError, match="vlm.check_drawing: true or false"):
        VLMSupervisor(model=str(lit_model), analyzer=fa, check_drawing="no")
