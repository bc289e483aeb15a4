"""scripts/average_weights.py on tiny real Qwen3-VL checkpoints: the weighted mean of every floating tensor, the
first checkpoint's other files, a model that loads; mismatched checkpoints and bad weights refused in one line."""

import json
import shutil
import sys

import pytest
import torch
from safetensors.torch import load_file, save_file

from tests.conftest import run


@pytest.fixture(scope="module")
def two(tmp_path_factory):
    """Two checkpoints of one architecture with different weights (the second's floats scaled and shifted)."""
    from labrobfail_vlm.model.tiny import build_tiny

    root = tmp_path_factory.mktemp("soup")
    a = build_tiny(root / "a")
    b = root / "b"
    shutil.copytree(a, b)
    w = load_file(str(b / "model.safetensors"))
    save_file({k: v * 3 + 1 if v.is_floating_point() else v for k, v in w.items()}, str(b / "model.safetensors"))
    (a / "eval_val").mkdir()  # a bench folder: not copied
    return a, b


def average(*args: str):
    return run([sys.executable, "scripts/average_weights.py", *args], 300)


def test_the_average_is_the_weighted_mean_and_loads(two, tmp_path):
    from labrobfail_vlm.model.loading import load_model

    a, b = two
    out = tmp_path / "soup"
    r = average(f"src=[{a},{b}]", "weights=[0.75,0.25]", f"out={out}")
    assert r.returncode == 0, r.stderr
    wa, wb, got = (load_file(str(p / "model.safetensors")) for p in (a, b, out))
    assert got.keys() == wa.keys()
    for k, v in got.items():
        assert v.dtype == wa[k].dtype and v.shape == wa[k].shape
        if v.is_floating_point():
            torch.testing.assert_close(v, (0.75 * wa[k].float() + 0.25 * wb[k].float()).to(v.dtype))
    k0 = next(k for k, v in got.items() if v.is_floating_point())
    assert not torch.equal(got[k0], wa[k0])  # a new model, not the first's copy
    assert (out / "chat_template.jinja").is_file() and not (out / "eval_val").exists()
    assert json.loads((out / "averaged_from.json").read_text())["weights"] == [0.75, 0.25]
    assert not (tmp_path / "soup.tmp").exists()
    load_model(out)  # a model folder transformers loads


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["weights=[0.5,0.6]"], "summing to 1"),
        (["weights=[1.0]"], "summing to 1"),
        (["weights=[a,b]"], "not a list of numbers"),
        (["weights=[nan,nan]"], "summing to 1"),
    ],
)
def test_bad_weights_are_refused_in_one_line_and_nothing_is_written(two, tmp_path, args, says):
    a, b = two
    r = average(f"src=[{a},{b}]", f"out={tmp_path / 'soup'}", *args)
    assert r.returncode == 2 and says in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not (tmp_path / "soup").exists()


def test_checkpoints_of_other_shapes_or_configs_and_an_existing_out_are_refused(two, tmp_path):
    a, b = two
    c = tmp_path / "c"
    shutil.copytree(b, c)
    w = load_file(str(c / "model.safetensors"))
    name = next(k for k, v in w.items() if v.is_floating_point() and v.dim() == 2)
    w[name] = w[name][:, :-1].contiguous()
    save_file(w, str(c / "model.safetensors"))
    r = average(f"src=[{a},{c}]", f"out={tmp_path / 'soup'}")
    assert r.returncode == 2 and f"tensor {name} differs in shape" in r.stderr, r.stderr
    assert not (tmp_path / "soup").exists()
    cfg = json.loads((c / "config.json").read_text())
    (c / "config.json").write_text(json.dumps({**cfg, "extra": 1}))
    r = average(f"src=[{a},{c}]", f"out={tmp_path / 'soup'}")
    assert r.returncode == 2 and "config.json differs" in r.stderr, r.stderr
    (c / "model.safetensors").write_bytes(b"not weights")
    (c / "config.json").write_text(json.dumps(cfg))
    r = average(f"src=[{a},{c}]", f"out={tmp_path / 'soup'}")
    assert r.returncode == 2 and "unreadable weights" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    (tmp_path / "soup").mkdir()
    r = average(f"src=[{a},{b}]", f"out={tmp_path / 'soup'}")
    assert r.returncode == 2 and "already exists" in r.stderr
    r = average(f"src=[{a}]", f"out={tmp_path / 'other'}")
    assert r.returncode == 2 and "two or more" in r.stderr
    r = average("src=3", f"out={tmp_path / 'other'}")
    assert r.returncode == 2 and "two or more" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


def _copy(src, dst, change=None, extra=None):
    """A copy of a checkpoint folder, its weights changed by `change` and `extra` tensors added."""
    shutil.copytree(src, dst)
    w = load_file(str(dst / "model.safetensors"))
    save_file({**(change(w) if change else w), **(extra or {})}, str(dst / "model.safetensors"))
    return dst


def test_a_failure_part_way_leaves_no_folder_and_other_folders_are_refused(two, tmp_path):
    """Tensors that cannot be averaged (a non-float one that differs), other weight files, a LoRA-tuned card: each
    refused in one line, with no <out> and no <out>.tmp left; an <out>.tmp already there is refused, not deleted."""
    a, b = two
    out = tmp_path / "soup"
    ia = _copy(a, tmp_path / "ia", extra={"steps": torch.tensor([1, 2])})
    ib = _copy(b, tmp_path / "ib", extra={"steps": torch.tensor([1, 3])})
    r = average(f"src=[{ia},{ib}]", f"out={out}")
    assert r.returncode == 2 and "non-float tensor steps differs" in r.stderr, r.stderr
    assert not out.exists() and not (tmp_path / "soup.tmp").exists()
    same = _copy(b, tmp_path / "same", extra={"steps": torch.tensor([1, 2])})
    assert average(f"src=[{ia},{same}]", f"out={out}").returncode == 0  # equal non-float tensors are kept
    assert torch.equal(load_file(str(out / "model.safetensors"))["steps"], torch.tensor([1, 2]))
    r = average(f"src=[{a},{ia}]", f"out={tmp_path / 'o2'}")
    assert r.returncode == 2 and "other tensor names" in r.stderr, r.stderr
    shutil.copy(b / "model.safetensors", same / "more.safetensors")
    r = average(f"src=[{a},{same}]", f"out={tmp_path / 'o2'}")
    assert r.returncode == 2 and ".safetensors files differ" in r.stderr, r.stderr
    lora = _copy(b, tmp_path / "lora")
    (lora / "labrobfail.json").write_text(json.dumps({"tuning": "hybrid", "grid": None}))
    r = average(f"src=[{a},{lora}]", f"out={tmp_path / 'o2'}")
    assert r.returncode == 2 and "tuned 'hybrid', not 'full'" in r.stderr, r.stderr
    (tmp_path / "o3.tmp").mkdir()
    (tmp_path / "o3.tmp" / "keep").write_text("mine")
    r = average(f"src=[{a},{b}]", f"out={tmp_path / 'o3'}")
    assert r.returncode == 2 and "o3.tmp exists" in r.stderr and (tmp_path / "o3.tmp" / "keep").is_file()
    assert not (tmp_path / "o2").exists() and not (tmp_path / "o2.tmp").exists()
