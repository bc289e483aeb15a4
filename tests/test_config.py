"""The shared command line (labrobfail_vlm/config.py): a list setting given a scalar is a one-line error."""

import subprocess
import sys

import pytest

from labrobfail_vlm.config import ConfigError, load_config

DEFAULTS = """
preset: plain
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
    ],
)
def test_a_scalar_for_a_list_is_refused(arg, msg):
    with pytest.raises(ConfigError, match=msg):
        load_config(DEFAULTS, ["preset=plain", arg])


def test_lists_strings_nulls_and_interpolations_pass_to_their_readers():
    cfg = load_config(DEFAULTS, ["preset=plain", "baselines=[]", "grid.views=[front,wrist]"])
    assert list(cfg.baselines) == [] and list(cfg.grid.views) == ["front", "wrist"]
    # a string or null is the reader's to take (a script may read "a,b" or null on purpose)
    assert load_config(DEFAULTS, ["preset=plain", "baselines=majority,blind"]).baselines == "majority,blind"
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
