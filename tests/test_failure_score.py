"""P(failure) from all four closed questions (FailureAnalyzer(failure_score="questions")): the mean of Q2's P("Yes")
and each of Q3-Q5's P(not "None"), checked against the tiny model's own scores of each question asked alone; the
verdict at the operating point, the one-pass and six-prompt paths, the checkpoint setting and labrobfail-calibrate's
copy that carries it."""

import json

import numpy as np
import pytest
from conftest import cli, evaluate, run_here
from PIL import Image
from test_option_bias import _checkpoint
from test_train import small_ds, tiny  # noqa: F401  (session fixtures)

TASK = "pick up the beaker"


def _alone(fa, img, dim, variant=0):  # noqa: ANN001
    """The softmax over `dim`'s admissible replies, its prompt (in wording `variant`) prefilled alone."""
    from labrobfail_vlm.option_bias import numbered_options

    opts = ("Yes", "No") if dim == "Q2" else ("None", *numbered_options(dim, fa.num_frames))
    prompt = fa._prompt(dim, TASK, variant)
    pre = fa.decoder.prefill(dict(fa.processor(text=[prompt], images=[img], return_tensors="pt")))
    z = np.asarray(fa.decoder.option_scores_rows(pre, [opts])[0])
    return np.exp(z - z.max()) / np.exp(z - z.max()).sum()


def test_the_questions_score_is_the_mean_of_four_detectors_on_both_paths(tiny, small_ds):  # noqa: F811
    from labrobfail_vlm.analyzer import FailureAnalyzer
    from labrobfail_vlm.failure_score import score_reads

    assert [len(score_reads(f, i)) for f in ("q2", "questions", "wordings") for i in (True, False)] == [
        1,
        1,
        4,
        4,
        18,
        18,
    ]

    imgs = [Image.open(p).convert("RGB") for p in sorted((small_ds / "images").glob("*.png"))[:3]]
    q2 = FailureAnalyzer.from_pretrained(tiny)
    fa = FailureAnalyzer.from_pretrained(tiny, failure_score="questions")
    for img in imgs:
        probs = [_alone(fa, img, "Q2")[0]] + [1.0 - _alone(fa, img, d)[0] for d in ("Q3", "Q4", "Q5")]
        one, six = fa.answers(img, TASK), fa.answers(img, TASK, one_pass=False)
        assert one.p_failure == pytest.approx(float(np.mean(probs)), abs=1e-4)
        assert six.p_failure == pytest.approx(one.p_failure, abs=1e-4) and dict(six) == dict(one)
        assert list(one) == ["Q1", "Q2", "Q3", "Q4", "Q5", "Q6"]  # the replies in the questions' order
        assert q2.answers(img, TASK).p_failure == pytest.approx(probs[0], abs=1e-4)  # the default: Q2 alone
        # the verdict is the mean's: an operating point just over it says "No", just under it "Yes"
        for cut, reply in ((one.p_failure + 1e-3, "No"), (one.p_failure - 1e-3, "Yes")):
            if 0.0 < cut < 1.0:
                fa.threshold = cut
                a = fa.answers(img, TASK)
                assert a["Q2"] == reply and (a["Q3"] == "None") == (reply == "No")
        fa.threshold = 0.5
    # every wording: 18 reads, a Q2 wording that asks about success read as its P("No")
    from labrobfail_vlm.questions import VARIANTS

    wf = FailureAnalyzer.from_pretrained(tiny, failure_score="wordings")
    reads = [
        (_alone(wf, imgs[0], d, v)[1] if VARIANTS[d][v].positive else _alone(wf, imgs[0], d, v)[0])
        if d == "Q2"
        else 1.0 - _alone(wf, imgs[0], d, v)[0]
        for d in ("Q2", "Q3", "Q4", "Q5")
        for v in range(len(VARIANTS[d]))
    ]
    w1, w6 = wf.answers(imgs[0], TASK), wf.answers(imgs[0], TASK, one_pass=False)
    assert len(reads) == 18 and w1.p_failure == pytest.approx(float(np.mean(reads)), abs=1e-4)
    assert w6.p_failure == pytest.approx(w1.p_failure, abs=1e-4) and dict(w6) == dict(w1)
    batch = fa.answers_batch(imgs, [TASK] * 3, frames=[None, 4, None])  # rows read as one at a time, Q3's
    alone = [fa.answers(i, TASK, frames=f) for i, f in zip(imgs, (None, 4, None))]  # options per row's frames
    assert [b.p_failure for b in batch] == pytest.approx([a.p_failure for a in alone], abs=1e-4)
    assert [dict(b) for b in batch] == [dict(a) for a in alone]
    assert fa.answers(imgs[0], TASK, dims=["Q2"]).keys() == {"Q2"}  # Q3-Q5 scored, not answered, when not asked


def test_the_checkpoint_names_its_failure_score_and_calibrate_writes_it(tiny, small_ds, tmp_path):  # noqa: F811
    from labrobfail_vlm.analyzer import FailureAnalyzer
    from labrobfail_vlm.config import ConfigError

    ck = _checkpoint(tiny, tmp_path / "q", {"tuning": "full", "failure_score": "questions"})
    assert FailureAnalyzer.from_pretrained(ck).failure_score == "questions"
    assert FailureAnalyzer.from_pretrained(ck, failure_score="q2").failure_score == "q2"  # the caller's wins
    # the bench reads it from the checkpoint and says so in its results
    fast = ("baselines=[]", "q6_template=false", "progress=false", "split=test")
    r = evaluate(f"model={ck}", small_ds, *fast, call=run_here)
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads((ck / "eval_test" / "results.json").read_text())["failure_score"] == "questions"
    bad = _checkpoint(tiny, tmp_path / "bad", {"tuning": "full", "failure_score": "vibes"})
    with pytest.raises(ConfigError, match="labrobfail.json: failure_score: expected one of q2, questions"):
        FailureAnalyzer.from_pretrained(bad)
    with pytest.raises(ValueError, match="failure_score"):
        FailureAnalyzer.from_pretrained(tiny, failure_score="Q2")
    # labrobfail-calibrate: dims=[] with a failure score fits nothing and writes the setting into the copy
    model = _checkpoint(tiny, tmp_path / "m", {"tuning": "full", "option_bias": {"Q4": [0.0, 1.0, 0.0, 0.0]}})
    out = tmp_path / "m_q"
    base = [cli("calibrate"), f"model={model}", f"dataset_dir={small_ds}", "check=[]", f"out={out}", "dims=[]"]
    for extra, needle in (
        (["failure_score=vibes"], "failure_score: expected one of"),
        ([], "dims: expected"),
        (["dims=null", "failure_score=questions"], "dims: expected"),
    ):
        r = run_here([*base, *extra])
        assert r.returncode == 2 and needle in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not out.exists()
    r = run_here([*base, "failure_score=questions"])
    assert r.returncode == 0, r.stderr[-2000:]
    man = json.loads((out / "labrobfail.json").read_text())
    assert man["failure_score"] == "questions" and man["option_bias"] == {"Q4": [0.0, 1.0, 0.0, 0.0]}
    assert "option_bias_fit" not in man and FailureAnalyzer.from_pretrained(out).failure_score == "questions"
