"""Option biases for Q3-Q5 (labrobfail_vlm/option_bias.py): the fit on known data, the analyzer's use of them, and
labrobfail-calibrate from a real bench of the tiny model to a checkpoint that answers with them."""

import json

import numpy as np
import pytest
from conftest import cli, evaluate, run_here
from PIL import Image
from test_train import small_ds, tiny  # noqa: F401  (session fixtures)

from labrobfail_vlm.option_bias import accuracy, biased_choice, check_option_bias, fit_bias


def test_bad_biases_are_one_line_and_ties_go_to_the_first_option():
    assert check_option_bias({"Q4": [0, 1.5, 0, 0]}) == {"Q4": (0.0, 1.5, 0.0, 0.0)} and check_option_bias(None) == {}
    for bad, needle in (
        ({"Q2": [0, 1]}, "keys among Q3, Q4, Q5"),
        ({"Q4": [0, float("nan")]}, "finite numbers"),
        ({"Q4": "0 1"}, "finite numbers"),
        ({"Q4": [True]}, "finite numbers"),
        ([0, 1], "mapping"),
        ({"Q5": [0, 1, 2]}, "expected 5 numbers"),
        ({"Q3": []}, "at least 1"),
    ):
        with pytest.raises(ValueError, match=needle):
            check_option_bias(bad)
    assert biased_choice([1.0, 1.0, 0.0]) == 0 and biased_choice([1.0, 1.0, 0.0], [0, 0, 1.0]) == 0
    assert biased_choice([1.0, 1.0, 0.0], [0, 0, 1.5]) == 2
    assert biased_choice([0.0, 0.2, 0.1, 0.0], [0.0, -0.5]) == 2  # an option past the bias's end counts 0


def test_likelihood_fit_recovers_a_known_prior_shift():
    """Gold drawn from softmax(logits); the model's scores are the logits minus a shift per option: the fitted bias
    is that shift (up to a constant), and it recovers the accuracy the shift cost."""
    rng = np.random.default_rng(0)
    logits = rng.normal(0, 2, (20000, 4))
    p = np.exp(logits) / np.exp(logits).sum(1, keepdims=True)
    gold = [int(rng.choice(4, p=row)) for row in p]
    shift = np.array([0.0, 1.0, -0.5, 2.0])
    scores = (logits - shift).tolist()
    b = fit_bias(scores, gold, 4, "likelihood", ridge=0.0)
    assert b[0] == 0 and np.allclose(b, shift, atol=0.1)
    assert accuracy(scores, gold, b) > accuracy(scores, gold) + 0.05
    assert fit_bias([], [], 3) == [0.0, 0.0, 0.0]


def test_accuracy_fit_moves_a_boundary_the_gold_answers_sit_past():
    """Option 2 always scores 0.3 under option 1 but is right 70 % of the time: the accuracy fit lifts it over."""
    scores = [[0.0, -0.3, -5.0]] * 10
    gold = [1] * 7 + [0] * 3
    b = fit_bias(scores + [[0.0, 0.0, 0.0]], gold + [7], 3, "accuracy")  # a gold past the options: skipped
    assert b[0] == 0 and 0.3 < b[1] <= 4 and accuracy(scores, gold, b) == 0.7 and accuracy(scores, gold) == 0.3
    with pytest.raises(ValueError, match="objective"):
        fit_bias(scores, gold, 3, "vibes")


def _checkpoint(tiny, root, manifest):  # noqa: F811
    """The tiny model as a fine-tuned checkpoint folder (its files linked) with `manifest` as labrobfail.json."""
    root.mkdir(parents=True)
    for f in tiny.iterdir():
        (root / f.name).symlink_to(f)
    (root / "labrobfail.json").write_text(json.dumps(manifest))
    return root


def test_the_analyzer_answers_with_the_bias_and_keeps_the_unbiased_scores(tiny, small_ds, tmp_path):  # noqa: F811
    from labrobfail_vlm.analyzer import FailureAnalyzer
    from labrobfail_vlm.config import ConfigError

    img = Image.open(sorted((small_ds / "images").glob("*.png"))[0]).convert("RGB")
    plain = FailureAnalyzer.from_pretrained(tiny, threshold=0.001)  # every grid called a failure: Q3-Q5 asked
    a = plain.answers(img, "pick up the beaker")
    assert set(a.option_scores) == {"Q3", "Q4", "Q5"} and len(a.option_scores["Q4"]) == 4
    assert a["Q4"] == str(int(np.argmax(a.option_scores["Q4"])) + 1)
    worst = {d: int(np.argmin(s)) for d, s in a.option_scores.items()}
    bias = {d: [50.0 if k == worst[d] else 0.0 for k in range(len(s))] for d, s in a.option_scores.items()}
    ck = _checkpoint(tiny, tmp_path / "cal", {"tuning": "full", "option_bias": bias})
    fa = FailureAnalyzer.from_pretrained(ck, threshold=0.001)
    b = fa.answers(img, "pick up the beaker")
    assert {d: b[d] for d in worst} == {d: str(k + 1) for d, k in worst.items()}
    assert all(b.option_scores[d] == pytest.approx(a.option_scores[d], abs=1e-4) for d in worst)
    assert b["Q1"] == a["Q1"] and b.p_failure == pytest.approx(a.p_failure, abs=1e-6)
    six = fa.answers(img, "pick up the beaker", one_pass=False)
    assert {d: six[d] for d in worst} == {d: b[d] for d in worst}  # the reference path applies it too
    assert all(six.option_scores[d] == pytest.approx(b.option_scores[d], abs=1e-4) for d in worst)
    bad = _checkpoint(tiny, tmp_path / "bad", {"tuning": "full", "option_bias": {"Q2": [0, 1]}})
    with pytest.raises(ConfigError, match="labrobfail.json: option_bias: expected keys"):
        FailureAnalyzer.from_pretrained(bad)
    short = _checkpoint(tiny, tmp_path / "short", {"tuning": "full", "option_bias": {"Q4": [0, 1]}})
    with pytest.raises(ConfigError, match="option_bias.Q4: expected 4 numbers"):
        FailureAnalyzer.from_pretrained(short)


def test_calibrate_writes_a_checkpoint_that_answers_with_its_biases(tiny, small_ds, tmp_path):  # noqa: F811
    """Fitted on a real val bench of the tiny model; the new checkpoint, benched, answers as the biases say."""
    from labrobfail_vlm.analyzer import FailureAnalyzer
    from labrobfail_vlm.bench import evaluate as ev
    from labrobfail_vlm.bench.calibrate import with_bias

    model = _checkpoint(tiny, tmp_path / "m", {"tuning": "full"})
    ds = tmp_path / "ds"  # the fixture's test records asked as its val split (the fixture's val split is empty)
    ds.mkdir()
    for f in small_ds.iterdir():
        if f.name != "val.json":
            (ds / f.name).symlink_to(f)
    (ds / "val.json").symlink_to(small_ds / "test.json")
    (ds / "val_object.json").symlink_to(small_ds / "test.json")
    fast = ("baselines=[]", "q6_template=false", "progress=false", "threshold=0.001")  # Q3-Q5 asked everywhere
    r = evaluate(f"model={model}", ds, "split=val", f"out_dir={model / 'eval_val'}", *fast, call=run_here)
    assert r.returncode == 0, r.stderr[-2000:]
    preds = ev.read_predictions(model / "eval_val" / "predictions.jsonl")
    assert preds.option_scores and {i.rsplit("_", 1)[1] for i in preds.option_scores} == {"Q3", "Q4", "Q5"}
    (model / "eval_val_object").mkdir()  # a bench written before the scores were kept: refused, not re-scored as 0
    old = [json.dumps({"id": k, "prediction": v}) + "\n" for k, v in preds.items()]
    (model / "eval_val_object" / "predictions.jsonl").write_text("".join(old))
    out = tmp_path / "m_cal"
    calibrate = [cli("calibrate"), f"model={model}", f"dataset_dir={ds}", "check=[]", "objective=accuracy"]
    for extra, needle in (
        (["check=[test]"], "validation splits only"),
        (["objective=vibes"], "objective: expected one of"),
        (["dims=[Q2]"], "dims: expected"),
        (["check=null"], "check: expected a list"),
        (["ridge=-1"], "ridge: expected a number"),
        ([f"out={model / 'inner'}"], "inside model="),
        (["check=[val_object]"], "no option scores for Q3, Q4, Q5"),
    ):
        r = run_here([*calibrate, f"out={out}", *extra])
        assert r.returncode == 2 and needle in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not out.exists()
    r = run_here([*calibrate, f"out={out}"])
    assert r.returncode == 0, r.stderr[-2000:]
    assert "| val (fitted on) | Q4 |" in r.stdout
    man = json.loads((out / "labrobfail.json").read_text())
    assert set(man["option_bias"]) == {"Q3", "Q4", "Q5"} and man["tuning"] == "full"
    assert not list(out.glob("eval_*")) and not (tmp_path / "m_cal.tmp").exists()
    assert FailureAnalyzer.from_pretrained(out).option_bias == {k: tuple(v) for k, v in man["option_bias"].items()}
    r = run_here([*calibrate, f"out={out}"])
    assert r.returncode == 2 and "exists" in r.stderr
    # the calibrated checkpoint, benched for real, answers as the biases applied to the plain model's scores do
    r = evaluate(f"model={out}", ds, "split=val", *fast, call=run_here)
    assert r.returncode == 0, r.stderr[-2000:]
    real = ev.read_predictions(out / "eval_val_t0.001" / "predictions.jsonl")
    assert dict(real) == dict(with_bias(preds, man["option_bias"]))
    res = json.loads((out / "eval_val_t0.001" / "results.json").read_text())
    assert res["option_bias"] == man["option_bias"]
    # and with biases that surely move replies: every Q4 answered 4, every Q5 answered 3
    forced = {"Q4": [0.0, 0.0, 0.0, 50.0], "Q5": [0.0, 0.0, 50.0, 0.0, 0.0]}
    fc = _checkpoint(tiny, tmp_path / "forced", {"tuning": "full", "option_bias": forced})
    r = evaluate(f"model={fc}", ds, "split=val", *fast, call=run_here)
    assert r.returncode == 0, r.stderr[-2000:]
    real = ev.read_predictions(fc / "eval_val_t0.001" / "predictions.jsonl")
    assert dict(real) == dict(with_bias(preds, forced)) != dict(preds)
    assert {v for k, v in real.items() if k.endswith(("_Q4", "_Q5"))} == {"4", "3"}
