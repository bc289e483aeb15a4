"""Checkpoint validation before any tensor is built (issue 33): bad config.json, oversized configs, truncated or
mismatched safetensors and bad fine-tuned checkpoints are one-line errors with exit code 2 from infer.py and
labrobfail-serve, and ConfigErrors from FailureAnalyzer.from_pretrained (the VLM supervisor's loader).

A `{}` config makes transformers build the default Qwen3-VL (~50 GB in float32): every case that could build a
model runs in a subprocess whose address space is capped (MEMORY_GUARD), so a regression fails the test with a
MemoryError instead of taking the machine down."""

import json
import resource
import shutil
import subprocess
from pathlib import Path

import pytest
from conftest import program, run
from PIL import Image
from test_train import tiny  # noqa: F401  (session fixture)

MEMORY_GUARD = 6 << 30  # bytes of address space; a tiny model's infer.py peaks at ~1.6 GB virtual (measured)
BUDGET_ENV = "LABROBFAIL_MAX_MODEL_GB"


def _cap_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_GUARD, MEMORY_GUARD))


def guarded(args, env_extra=None, timeout=300, **kw):
    import os

    env = {k: v for k, v in os.environ.items() if k != BUDGET_ENV}
    env.update(env_extra or {})
    return run([*program(args[0]), *args[1:]], timeout, preexec_fn=_cap_memory, env=env, **kw)


# One capped process runs many cases in turn (run_here: each console script's entry point from sys.argv to its exit
# code), with one Python start and torch import for all of them instead of one per case.
_CASES_CHILD = r"""
import json, os, sys
sys.path.insert(0, sys.argv[1])
from conftest import run_here
out = []
for argv, env in json.loads(sys.stdin.read()):
    saved = dict(os.environ)
    os.environ.update(env)
    r = run_here(argv)
    os.environ.clear()
    os.environ.update(saved)
    out.append([r.returncode, r.stdout, r.stderr])
print(json.dumps(out))
"""


def guarded_cases(cases: list) -> list:
    """guarded() of each (args, env) in one capped process: the CompletedProcess of each, in order."""
    todo = [[program(args[0])[-1], *map(str, args[1:])] for args, _ in cases]
    r = guarded(
        ["-c", _CASES_CHILD, str(Path(__file__).parent)], input=json.dumps(list(zip(todo, [e for _, e in cases])))
    )
    assert r.returncode == 0, r.stderr[-1500:]
    return [
        subprocess.CompletedProcess(a, c, o, e) for a, (c, o, e) in zip(todo, json.loads(r.stdout.splitlines()[-1]))
    ]


def _clone(src, dst, config=None, raw=None):
    shutil.copytree(src, dst)
    if config is not None:
        (dst / "config.json").write_text(json.dumps(config))
    if raw is not None:
        (dst / "config.json").write_text(raw)
    return dst


def hybrid_checkpoint(base, out):
    """A real hybrid checkpoint (LoRA adapter + vision weights + manifest) over `base`, written as training does."""
    from labrobfail_vlm.model.hybrid import apply_tuning
    from labrobfail_vlm.model.loading import load_model
    from labrobfail_vlm.train.checkpoint import save_trainable

    model = apply_tuning(load_model(base), "hybrid", {"r": 4, "alpha": 8, "dropout": 0.0})
    save_trainable(model, out, model.state_dict(), str(base), "hybrid")
    for f in ("tokenizer.json", "tokenizer_config.json", "chat_template.jinja", "processor_config.json"):
        if (base / f).is_file():
            shutil.copy(base / f, out / f)
    return out


@pytest.fixture(scope="module")
def bad_models(tiny, tmp_path_factory):  # noqa: F811
    """(name, directory, environment, expected words) for every bad case; built without loading the bad ones."""
    root = tmp_path_factory.mktemp("bad")
    cfg = json.loads((tiny / "config.json").read_text())
    arch = {"model_type": "qwen3_vl", "architectures": ["Qwen3VLForConditionalGeneration"]}
    trunc = _clone(tiny, root / "truncated")
    data = (trunc / "model.safetensors").read_bytes()
    (trunc / "model.safetensors").write_bytes(data[: len(data) // 2])
    empty = _clone(tiny, root / "empty", config={})
    hybrid = hybrid_checkpoint(tiny, root / "hybrid_ok")
    over_empty = root / "hybrid_over_empty"
    shutil.copytree(hybrid, over_empty)
    man = json.loads((over_empty / "labrobfail.json").read_text())
    (over_empty / "labrobfail.json").write_text(json.dumps({**man, "base_model": str(empty)}))
    return [
        ("empty config", empty, {}, "has no model_type"),
        (
            "other model_type",
            _clone(tiny, root / "llama", config={**cfg, "model_type": "llama", "architectures": ["LlamaForCausalLM"]}),
            {},
            "model_type 'llama'",
        ),
        (
            "other architecture",
            _clone(tiny, root / "arch", config={**cfg, "architectures": ["Qwen3VLModel"]}),
            {},
            "architectures ['Qwen3VLModel']",
        ),
        ("list config", _clone(tiny, root / "list", config=[cfg]), {}, "holds a JSON list"),
        ("non-JSON config", _clone(tiny, root / "notjson", raw="{model_type: qwen3_vl"), {}, "not valid JSON"),
        ("truncated safetensors", trunc, {}, "is truncated"),
        (
            "mismatched shapes",
            _clone(
                tiny, root / "shapes", config={**cfg, "text_config": {**cfg["text_config"], "intermediate_size": 512}}
            ),
            {},
            "does not match config.json",
        ),
        (
            "more layers than weights",
            _clone(
                tiny, root / "layers", config={**cfg, "text_config": {**cfg["text_config"], "num_hidden_layers": 3}}
            ),
            {},
            "lacks",
        ),
        # the default Qwen3-VL (what a config naming no sizes becomes): 12.6 B parameters, ~50 GB in float32
        (
            "too large for the budget",
            _clone(tiny, root / "defaults", config=arch),
            {BUDGET_ENV: "8"},
            "over the 8.0 GB model memory budget",
        ),
        ("fine-tuned over an empty-config base", over_empty, {}, "base_model of"),
    ]


def _one_line_error(r, needle, what):
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2, (what, r.returncode, r.stderr[-800:])
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in r.stderr, (what, r.stderr[-800:])
    assert lines[0].startswith(("error: model:", "error: model (")), (what, lines[0])


def test_infer_refuses_bad_checkpoints_in_one_line(bad_models, tmp_path):
    Image.new("RGB", (256, 128), (9, 9, 9)).save(tmp_path / "g.png")
    cases = [(["infer.py", "--grid", tmp_path / "g.png", "--model", model], env) for _, model, env, _ in bad_models]
    r = guarded(*cases[0])  # the first case as its own process, then all of them in one
    _one_line_error(r, bad_models[0][3], bad_models[0][0])
    for r, (what, _, _, needle) in zip(guarded_cases(cases), bad_models):
        _one_line_error(r, needle, what)
        assert r.stdout == "", what


def test_serve_refuses_bad_checkpoints_at_start(bad_models):
    cases = [(["labrobfail-serve", "--model", model, "--port", "0"], env) for _, model, env, _ in bad_models]
    r = guarded(*cases[0], timeout=120)  # the first case as its own process, then all of them in one
    _one_line_error(r, bad_models[0][3], bad_models[0][0])
    for r, (what, _, _, needle) in zip(guarded_cases(cases), bad_models):
        _one_line_error(r, needle, what)
        assert "serving" not in r.stdout, what


def test_budget_argument_and_good_checkpoints(tiny, bad_models, tmp_path):  # noqa: F811
    """--max-model-gb overrides the default; a good base and a good fine-tuned checkpoint still diagnose."""
    Image.new("RGB", (256, 128), (9, 9, 9)).save(tmp_path / "g.png")
    hybrid = next(m for what, m, *_ in bad_models if m.name == "hybrid_over_empty").parent / "hybrid_ok"
    infer = ["infer.py", "--grid", tmp_path / "g.png", "--model"]
    small, bad, served, *good = guarded_cases(
        [
            ([*infer, tiny, "--max-model-gb", "0.001"], {}),
            ([*infer, tiny, "--max-model-gb", "-1"], {}),
            (["labrobfail-serve", "--model", tiny, "--max-model-gb", "0.001"], {}),
            ([*infer, tiny], {}),
            ([*infer, hybrid], {}),
        ]
    )
    _one_line_error(small, "over the 1.0 MB model memory budget", "argument")
    assert bad.returncode == 2 and "max_model_gb: expected a positive number" in bad.stderr, bad.stderr[-500:]
    _one_line_error(served, "over the 1.0 MB model memory budget", "serve argument")
    for r in good:
        assert r.returncode == 0 and json.loads(r.stdout)["raw"]["Q2"] in ("Yes", "No"), r.stderr[-800:]


def test_from_pretrained_and_the_vlm_supervisor_validate_first(bad_models):
    """The supervisor loads through FailureAnalyzer.from_pretrained: same checks, a ConfigError (one line)."""
    code = r"""
import json, os, sys
from labrobfail_vlm.config import ConfigError
from sim_backends.supervision.vlm import VLMSupervisor
out = []
for model, env in json.loads(sys.stdin.read()):
    os.environ.update(env)
    try:
        VLMSupervisor(model=model)
        out.append("loaded")
    except ConfigError as e:
        out.append(str(e))
    for k in env:
        del os.environ[k]
print(json.dumps(out))
"""
    cases = [c for c in bad_models if c[0] in ("empty config", "truncated safetensors", "too large for the budget")]
    r = guarded(["-c", code], input=json.dumps([[str(model), env] for _, model, env, _ in cases]))
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr[-1500:]
    for msg, (what, _, _, needle) in zip(json.loads(r.stdout.splitlines()[-1]), cases, strict=True):
        assert needle in msg and "\n" not in msg, (what, msg)


def test_parameter_estimate_equals_the_real_model():
    """expected_tensors (config arithmetic) == the state dict of Qwen3VLForConditionalGeneration built on the meta
    device (no memory), for the tiny preset, tied embeddings, attention bias, three deepstack mergers and the
    default 12.6 B config. In a guarded subprocess: were the meta device ignored, the default would need ~50 GB."""
    code = r"""
import json, sys, torch
from transformers import Qwen3VLConfig, Qwen3VLForConditionalGeneration
from labrobfail_vlm.model.loading import count_params, expected_tensors
from labrobfail_vlm.model.tiny import TINY_TEXT, TINY_VISION
tiny = {"model_type": "qwen3_vl", "text_config": {**TINY_TEXT, "vocab_size": 1024},
        "vision_config": {**TINY_VISION, "out_hidden_size": TINY_TEXT["hidden_size"]}}
cases = [tiny, {**tiny, "tie_word_embeddings": True},
         {**tiny, "text_config": {**tiny["text_config"], "attention_bias": True}},
         {**tiny, "vision_config": {**tiny["vision_config"], "depth": 3, "deepstack_visual_indexes": [0, 1, 2]}},
         {"model_type": "qwen3_vl"}]
out = []
for c in cases:
    cfg = Qwen3VLConfig.from_dict(c)
    with torch.device("meta"):
        model = Qwen3VLForConditionalGeneration(cfg)
    real = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    if cfg.tie_word_embeddings:
        real.pop("lm_head.weight", None)
    est = expected_tensors(cfg)
    out.append([est == real, count_params(est), sum(p.numel() for p in model.parameters())])
print(json.dumps(out))
"""
    r = guarded(["-c", code])
    assert r.returncode == 0, r.stderr[-1500:]
    rows = json.loads(r.stdout.strip().splitlines()[-1])
    assert all(same and est == real for same, est, real in rows), rows
    assert rows[-1][1] == 12_616_410_352  # the default config: why `{}` must never reach the loader


def test_fine_tuned_and_sharded_checkpoints_are_checked_piece_by_piece(tiny, bad_models, tmp_path):  # noqa: F811
    """In process: validation reads headers and JSON only. Each piece of a fine-tuned or sharded checkpoint that
    would fail (or load garbage) later is named in the error."""
    from labrobfail_vlm.config import ConfigError
    from labrobfail_vlm.model.loading import validate_model_dir
    from labrobfail_vlm.train.checkpoint import validate_checkpoint

    good = next(m for _, m, *_ in bad_models if m.name == "hybrid_over_empty").parent / "hybrid_ok"
    assert validate_checkpoint(good).params > validate_checkpoint(tiny).params  # the adapter counts too

    def broken(name, edit):
        d = tmp_path / name
        shutil.copytree(good, d)
        edit(d)
        with pytest.raises(ConfigError) as e:
            validate_checkpoint(d)
        return str(e.value)

    def cut(f):
        f.write_bytes(f.read_bytes()[:-100])

    def manifest(d, **kw):
        (d / "labrobfail.json").write_text(json.dumps({**json.loads((d / "labrobfail.json").read_text()), **kw}))

    assert "adapter_model.safetensors is truncated" in broken("a", lambda d: cut(d / "adapter_model.safetensors"))
    assert "vision_merger.safetensors is truncated" in broken("v", lambda d: cut(d / "vision_merger.safetensors"))
    assert "tuning 'lora'" in broken("t", lambda d: manifest(d, tuning="lora"))
    assert "no such model directory" in broken("b", lambda d: manifest(d, base_model=str(tmp_path / "gone")))
    assert "holds a JSON list" in broken("m", lambda d: (d / "labrobfail.json").write_text("[]"))
    assert "adapter_config.json is not a JSON object" in broken(
        "c", lambda d: (d / "adapter_config.json").write_text("nope")
    )
    # an adapter trained on another base: its LoRA shapes do not fit this base's layers
    other = tmp_path / "other_base"
    from labrobfail_vlm.model.tiny import build_tiny

    build_tiny(other, text={"intermediate_size": 192})
    assert "does not fit the base weight" in broken("o", lambda d: manifest(d, base_model=str(other)))

    # sharded weights: the index and every shard are checked
    from labrobfail_vlm.model.loading import load_model

    sharded = tmp_path / "sharded"
    shutil.copytree(tiny, sharded)
    (sharded / "model.safetensors").unlink()
    load_model(tiny).save_pretrained(sharded, max_shard_size="1MB")
    shards = sorted(sharded.glob("model-*.safetensors"))
    assert len(shards) > 1 and validate_model_dir(sharded).params == validate_checkpoint(tiny).params
    cut(shards[-1])
    with pytest.raises(ConfigError, match="is truncated"):
        validate_model_dir(sharded)
    shards[-1].unlink()
    with pytest.raises(ConfigError, match="which is missing"):
        validate_model_dir(sharded)
