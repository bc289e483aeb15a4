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
        ("baselines=null", "baselines: expected a list .* got None"),
        ("baselines=majority", "baselines: expected a list .* got 'majority'"),
        ("grid.views=front", "grid.views: expected a list .* got 'front'"),
    ],
)
def test_a_scalar_for_a_list_is_refused(arg, msg):
    with pytest.raises(ConfigError, match=msg):
        load_config(DEFAULTS, ["preset=plain", arg])


def test_lists_and_a_null_that_the_defaults_allow_pass():
    cfg = load_config(DEFAULTS, ["preset=plain", "baselines=[]", "grid.views=[front,wrist]"])
    assert list(cfg.baselines) == [] and list(cfg.grid.views) == ["front", "wrist"]
    # a list only in the preset, null in the defaults: null may be given back ("every scenario")
    assert load_config(DEFAULTS, ["preset=demo", "scenarios=null"]).scenarios is None
    assert list(load_config(DEFAULTS, ["preset=demo"]).scenarios) == ["pick", "place"]


def test_the_bench_says_it_in_one_line(tmp_path):
    """Before the fix, `labrobfail-evaluate baselines=false` died in the bench with a TypeError traceback."""
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
