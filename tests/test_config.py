"""The shared command line (labrobfail_vlm/config.py): a value of the wrong shape for its default (a scalar for a
list, a list for a number, anything but true/false for a bool) is a one-line error; a string for a list is a
comma-separated list."""

import subprocess
import sys

import pytest

from labrobfail_vlm.config import ConfigError, load_config

DEFAULTS = """
preset: plain
seed: 0
lr: 0.1
progress: true
resume: false
baselines: [majority, blind]
scenarios: null
grid: {views: [front, side]}
presets:
  plain: {}
  demo: {scenarios: [pick, place]}
"""


@pytest.mark.parametrize(
    "arg, msg",
    [
        ("baselines=false", "baselines: expected a list .* got False"),
        ("baselines=3", "baselines: expected a list .* got 3"),
        ("grid.views=0.5", "grid.views: expected a list .* got 0.5"),
        ("seed=[1]", "seed: expected one value, got a list"),  # a reader's int() raised a TypeError
        ("lr={a: 1}", "lr: expected one value, got a mapping"),
        ("progress=maybe", "progress: expected true or false, got 'maybe'"),  # was taken as true
        ("progress=0", "progress: expected true or false, got 0"),
        ("resume=[a]", "resume: expected one value, got a list"),
        ("seed=[1", "seed: not a valid setting"),  # the parser's message named no setting
        ("lr=fast", "lr: expected a number, got 'fast'"),  # a reader's float() named no setting
    ],
)
def test_a_value_of_the_wrong_shape_is_refused(arg, msg):
    with pytest.raises(ConfigError, match=msg):
        load_config(DEFAULTS, ["preset=plain", arg])


def test_lists_strings_nulls_and_interpolations_pass_to_their_readers():
    cfg = load_config(DEFAULTS, ["preset=plain", "baselines=[]", "grid.views=[front,wrist]"])
    assert list(cfg.baselines) == [] and list(cfg.grid.views) == ["front", "wrist"]
    # a string for a list is a comma-separated list (iterated, "front" would be five one-letter views); null stays
    assert list(load_config(DEFAULTS, ["preset=plain", "baselines=majority,blind"]).baselines) == ["majority", "blind"]
    assert list(load_config(DEFAULTS, ["preset=plain", "grid.views=front"]).grid.views) == ["front"]
    assert list(load_config(DEFAULTS, ["preset=plain", "baselines=0.2,5"]).baselines) == [0.2, 5]  # numbers stay
    # a bool that also takes a path (train's resume=<checkpoint>) takes it; a number takes an int
    assert load_config(DEFAULTS, ["resume=outputs/run/checkpoint-8", "lr=1", "progress=false"]).resume.endswith("-8")
    assert load_config(DEFAULTS, ["lr=inf"]).lr == "inf"  # a number YAML reads as text is the reader's
    assert load_config(DEFAULTS, ["preset=demo", "scenarios=null"]).scenarios is None
    assert list(load_config(DEFAULTS, ["preset=demo"]).scenarios) == ["pick", "place"]
    # an interpolation resolves after the merge, against the whole configuration
    assert list(load_config(DEFAULTS, ["preset=plain", "baselines=${grid.views}"]).baselines) == ["front", "side"]


def test_the_bench_says_it_in_one_line(tmp_path):
    """`labrobfail-evaluate baselines=false` (the bench iterated the bool: a TypeError traceback once past its other
    checks) is refused before anything else is read."""
    code = "import sys; from labrobfail_vlm.bench.cli import cli; cli()"
    r = subprocess.run(
        [sys.executable, "-c", code, f"model={tmp_path}", f"dataset_dir={tmp_path}", "baselines=false"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines() == [
        "error: baselines: expected a list (e.g. 'baselines=[majority,blind]' or 'baselines=[]'), got False"
    ]


def test_a_checkpoints_recorded_settings_are_compared_leaf_by_leaf_and_a_key_on_one_side_is_named(tmp_path):
    """labrobfail-train's resume check (train/resume.py) on records as checkpoints hold them: equal settings pass;
    a setting freed since the record was made (here `epochs`) is not compared; a key only one side has and a value
    that differs are one line each naming the key; a record that is not a JSON object is unreadable, not a diff."""
    import json

    from labrobfail_vlm.train.resume import SETTINGS_FILE, check_same_settings, run_settings

    cfg = load_config(DEFAULTS, [])
    now = run_settings(cfg)
    assert "resume" not in now and "progress" not in now and now["grid"] == {"views": ["front", "side"]}
    f = tmp_path / SETTINGS_FILE
    f.write_text(json.dumps(now | {"epochs": 9}))
    check_same_settings(tmp_path, now)
    f.write_text(json.dumps(now | {"lr": 0.2}))
    with pytest.raises(ConfigError, match=r"^lr: .* trained with 0.2, this run has 0.1; rerun with its settings"):
        check_same_settings(tmp_path, now)
    f.write_text(json.dumps({k: v for k, v in now.items() if k != "seed"}))
    with pytest.raises(ConfigError, match="^seed: .* by a labrobfail-train without this setting"):
        check_same_settings(tmp_path, now)
    f.write_text("[1, 2]")
    with pytest.raises(ConfigError, match="^resume: .* is not a readable settings record"):
        check_same_settings(tmp_path, now)
