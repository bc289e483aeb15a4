"""What the simulator drew into a model's training grids (the lamp, broken glass) travels from the shards' run.json
to the dataset, the checkpoint and labrobfail-supervise, which refuses a world drawn otherwise."""

import json
import shutil

import pytest
from conftest import cli, gen, run_here
from test_train import SMALL_GRID, small_ds, tiny  # noqa: F401  (session fixtures: a built dataset, a tiny Qwen3-VL)

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
    assert drawing.mismatches(lit, {"button_lamp": True}) == ["broken_glass"]  # absent: the backend's off
    assert drawing.mismatches({"broken_glass": "mixed", "button_lamp": False}, {"broken_glass": True}) == []
    assert drawing.mismatches(None, {"button_lamp": True}) == []


def test_a_run_json_says_what_was_drawn(tmp_path):
    for name, run in [("lit", {"backend_kwargs": {"button_lamp": True}}), ("silent", {"seed": 0}), ("none", None)]:
        (tmp_path / name).mkdir()
        if run is not None:
            (tmp_path / name / "run.json").write_text(json.dumps(run))
    assert drawing.of_shards(tmp_path / "lit") == {"broken_glass": False, "button_lamp": True}
    assert drawing.of_shards(tmp_path / "silent") is None and drawing.of_shards(tmp_path / "none") is None


def test_a_dataset_and_its_trained_checkpoints_record_the_drawing(run6, small_ds, tiny, tmp_path):  # noqa: F811
    from labrobfail_vlm.train.checkpoint import trained_drawing

    assert json.loads((small_ds / "stats.json").read_text())["drawing"] == OFF  # run6: generated with defaults
    lit = tmp_path / "lit_shards"
    gen(
        lit,
        "num_episodes=2",
        "scenarios=[press_button_red]",
        "backend_kwargs.button_lamp=true",
        "first_pair=100",
        here=True,
    )
    both = tmp_path / "both"
    r = run_here([cli("build-dataset"), f"shards=[{run6},{lit}]", f"out_dir={both}", "progress=false", *SMALL_GRID])
    assert r.returncode == 0, r.stderr
    assert json.loads((both / "stats.json").read_text())["drawing"] == {"broken_glass": False, "button_lamp": "mixed"}
    quiet = ["global_batch=2", "per_device_batch=2", "wandb.enabled=false", "progress=false", "max_steps=1"]
    first = tmp_path / "run"
    argv = ["train.py", "preset=tiny", "tower=scratch", *quiet]
    r = run_here([*argv, f"model.path={tiny}", f"dataset_dir={small_ds}", f"output_dir={first}"])
    assert r.returncode == 0, r.stderr
    assert trained_drawing(first / "final") == OFF
    assert trained_drawing(tiny) is None  # a base model: nothing recorded, nothing checked
    # a stage from that model on lit data alone: the model learned from both, so the lamp is "mixed"
    lit_ds = tmp_path / "lit_ds"
    r = run_here([cli("build-dataset"), f"shards={lit}", f"out_dir={lit_ds}", "progress=false", *SMALL_GRID])
    assert r.returncode == 0, r.stderr
    assert json.loads((lit_ds / "stats.json").read_text())["drawing"] == {"broken_glass": False, "button_lamp": True}
    second = tmp_path / "stage"
    r = run_here([*argv, f"model.path={first / 'final'}", f"dataset_dir={lit_ds}", f"output_dir={second}"])
    assert r.returncode == 0, r.stderr
    assert trained_drawing(second / "final") == {"broken_glass": False, "button_lamp": "mixed"}


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
        "error: vlm.model: its training grids were drawn with button_lamp=true, this run's with button_lamp=false "
        "(give backend_kwargs the same, or vlm.check_drawing=false to supervise anyway)"
    )
    assert not (out / "log.jsonl").exists()  # refused before the first trial
    r = run_here(
        [
            *argv,
            "image_size=48",
            "cameras=[front]",
            "progress=false",
            f"out_dir={out}",
            "backend_kwargs.button_lamp=true",
            "baseline=false",
            "loop.query_every=-1",
        ]
    )
    assert r.returncode == 0, r.stderr  # the same world as the training grids: supervised
    assert json.loads((out / "results.json").read_text())["tasks"]["press_button_red"]["vlm"]["trials"] == 1
    from labrobfail_vlm.analyzer import FailureAnalyzer
    from sim_backends.supervision.vlm import VLMSupervisor

    fa = FailureAnalyzer.from_pretrained(lit_model)
    VLMSupervisor(model=str(lit_model), analyzer=fa).check_drawing({"button_lamp": True, "broken_glass": True})
    with pytest.raises(ConfigError, match="button_lamp=true"):
        VLMSupervisor(model=str(lit_model), analyzer=fa).check_drawing({"broken_glass": True})
    VLMSupervisor(model=str(lit_model), analyzer=fa, check_drawing=False).check_drawing({})
    with pytest.raises(ConfigError, match="vlm.check_drawing: true or false"):
        VLMSupervisor(model=str(lit_model), analyzer=fa, check_drawing="no")


def test_the_drawing_check_is_not_part_of_a_runs_settings_digest():
    """vlm.check_drawing only refuses a run before its first trial: flipping it resumes the same trials (a dotted
    PER_RUN key), while a setting inside the same section that changes trials still tells runs apart."""
    from labrobfail_vlm.config import load_config
    from sim_backends.supervision.resume import fingerprint

    base = ["supervisor=vlm", "vlm.model=outputs/none"]
    a, b, c = (
        load_config("supervise.yaml", [*base, *x]) for x in ([], ["vlm.check_drawing=false"], ["vlm.threshold=0.3"])
    )
    assert fingerprint(a, ["vlm", "oracle"]) == fingerprint(b, ["vlm", "oracle"])
    assert fingerprint(a, ["vlm", "oracle"]) != fingerprint(c, ["vlm", "oracle"])
