"""infer.py, the structured decoder (one pass == six prompts), bad inputs, and the bench evaluator."""

import json
import shutil
import sys

import numpy as np
import pytest
import torch
from conftest import cli, evaluate, run, run_here
from PIL import Image
from test_train import small_ds, tiny  # noqa: F401  (session fixtures)

KEYS = {
    "task",
    "actions",
    "failure",
    "failure_frame",
    "severity",
    "severity_name",
    "category",
    "category_name",
    "correction",
    "correction_strategy",
    "primitives",
    "raw",
    "p_failure",
    "severity_main_text",
}


def infer(*args, here: bool = False):
    """infer.py as a process (or in this one: run_here)."""
    argv = [sys.executable, "infer.py", *args]
    return run_here(argv) if here else run(argv, 300)


@pytest.fixture(scope="module")
def grid(small_ds):  # noqa: F811
    return next((small_ds / "images").glob("*.png"))


def test_infer_prints_a_valid_diagnosis(tiny, grid, tmp_path):  # noqa: F811
    r = infer(
        "--grid", str(grid), "--model", str(tiny), "--task", "press the red button", "--json", str(tmp_path / "d.json")
    )
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert set(d) == KEYS and d == json.loads((tmp_path / "d.json").read_text())
    assert set(d["actions"]) <= {"grasp", "place", "open", "close", "pour", "shake", "insert", "stir"}
    assert d["raw"]["Q2"] in ("Yes", "No") and isinstance(d["failure"], bool)
    assert 0.0 <= d["p_failure"] <= 1.0 and d["failure"] == (d["p_failure"] >= 0.5)  # the score behind the verdict
    if d["failure"]:
        assert d["severity_main_text"] == ["Minor", "Recoverable", "Critical", "Catastrophic"][d["severity"] - 1]
        assert 1 <= d["failure_frame"] <= 16 and 1 <= d["severity"] <= 4 and 1 <= d["category"] <= 5
    else:
        assert d["failure_frame"] is None and d["raw"]["Q3"] == "None"


def test_one_pass_matches_six_prompts(tiny, small_ds):  # noqa: F811
    from labrobfail_vlm.analyzer import FailureAnalyzer

    fa = FailureAnalyzer.from_pretrained(tiny)
    for p in sorted((small_ds / "images").glob("*.png"))[:2]:
        img = Image.open(p).convert("RGB")
        one, six = (
            fa.answers(img, "pick up the beaker", one_pass=True),
            fa.answers(img, "pick up the beaker", one_pass=False),
        )
        assert one == six and one.p_failure == pytest.approx(six.p_failure, abs=1e-4)


def test_threshold_moves_the_verdict_and_q3_q6_follow_it(tiny, grid):  # noqa: F811
    """P(failure) is the softmax of the Yes/No scores; the operating point decides Q2, and Q3-Q6 follow it."""
    from labrobfail_vlm.analyzer import FailureAnalyzer
    from labrobfail_vlm.failure_score import p_yes

    fa = FailureAnalyzer.from_pretrained(tiny)
    img = Image.open(grid).convert("RGB")
    d = fa.analyze(img, "pick up the beaker")
    assert p_yes(("Yes", "No"), [np.log(0.2), np.log(0.6)]) == pytest.approx(0.25)
    fa.threshold = min(0.999, d.p_failure + 1e-3) if d.p_failure < 0.999 else 0.999
    low = fa.analyze(img, "pick up the beaker")
    fa.threshold = max(1e-3, d.p_failure - 1e-3)
    high = fa.analyze(img, "pick up the beaker")
    assert low.p_failure == pytest.approx(high.p_failure, abs=1e-6) == pytest.approx(d.p_failure, abs=1e-6)
    assert not low.failure and low.raw["Q3"] == "None" and high.failure and high.failure_frame is not None
    with pytest.raises(ValueError, match="threshold"):
        FailureAnalyzer(fa.model, fa.processor, threshold=1.0)


def test_frames_folder_builds_the_grid(tiny, tmp_path):  # noqa: F811
    rng = np.random.default_rng(0)
    for view in ("front", "side"):
        (tmp_path / "f" / view).mkdir(parents=True)
        for i in range(5):
            Image.fromarray(rng.integers(0, 255, (64, 64, 3), dtype=np.uint8)).save(tmp_path / "f" / view / f"{i}.png")
    r = infer("--frames", str(tmp_path / "f"), "--model", str(tiny), here=True)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["failure_frame"] in (None, 1, 2, 3, 4, 5)


def _unreadable(tmp):
    """A file this process cannot read: mode 000 for a normal user; as root (which ignores modes) the
    process's own /proc/self/mem, whose first page is unmapped, so reading it fails with EIO."""
    import os

    if os.geteuid() != 0:
        p = tmp / "locked.png"
        Image.new("RGB", (64, 64)).save(p)
        p.chmod(0)
        return str(p)
    return "/proc/self/mem"


def _bad_inputs(tmp, tiny):  # noqa: F811
    (tmp / "notimg.png").write_text("hello, I am text")
    (tmp / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4)
    Image.new("RGB", (256, 128), (9, 9, 9)).save(tmp / "ok.png")
    full = (tmp / "ok.png").read_bytes()
    (tmp / "trunc.png").write_bytes(full[: len(full) // 2])
    Image.new("RGB", (8, 8)).save(tmp / "tiny.png")
    Image.new("1", (9000, 5000)).save(tmp / "bomb.png")
    (tmp / "incomplete").mkdir()
    (tmp / "incomplete" / "config.json").write_text("{}")
    (tmp / "incomplete" / "tokenizer.json").write_text("{}")
    for v, n in (("a", 3), ("b", 2)):
        (tmp / "uneq" / v).mkdir(parents=True)
        for i in range(n):
            Image.new("RGB", (64, 64)).save(tmp / "uneq" / v / f"{i}.png")
    m = ["--model", str(tiny)]
    return [
        (["--grid", str(tmp / "missing.png"), *m], "does not exist"),
        (["--grid", _unreadable(tmp), *m], "not readable"),
        (["--grid", str(tmp / "notimg.png"), *m], "not an image"),
        (["--grid", str(tmp / "corrupt.png"), *m], "grid:"),
        (["--grid", str(tmp / "trunc.png"), *m], "truncated"),
        (["--grid", str(tmp), *m], "is a directory"),
        (["--grid", str(tmp / "tiny.png"), *m], "at least 32 px"),
        (["--grid", str(tmp / "bomb.png"), *m], "too large"),
        (["--grid", str(tmp / "ok.png"), "--model", str(tmp / "nomodel")], "no such model directory"),
        (["--grid", str(tmp / "ok.png"), "--model", str(tmp / "incomplete")], "no .safetensors weights"),
        (["--frames", str(tmp / "uneq"), *m], "unequal numbers of frames"),
        (["--frames", str(tmp / "ok.png"), *m], "not a directory"),
        (["--grid"], "grid: expected a path"),
    ]


def test_bad_inputs_are_one_line_errors(tiny, tmp_path):  # noqa: F811
    for i, (args, needle) in enumerate(_bad_inputs(tmp_path, tiny)):
        r = infer(*args) if i == 0 else run_here([sys.executable, "infer.py", *args])  # the first as a process
        assert r.returncode == 2, (args, r.stderr[-500:])
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in r.stderr and needle in lines[0], (args, r.stderr[-500:])


# ---- bench --------------------------------------------------------------------------------------------------
def test_bleu_and_rouge_equal_the_reference_libraries():
    from nltk.translate.bleu_score import SmoothingFunction, corpus_bleu
    from rouge_score import rouge_scorer

    from labrobfail_vlm.bench.metrics import bleu, rouge_l, tokens

    refs = ["Keep the gripper closed and move the arm to the target area.", "Open the gripper to release it."]
    hyps = ["Keep gripper closed, move the arm to the target.", "Close the gripper firmly."]
    ours = bleu(refs, hyps)
    for n in range(1, 5):
        want = corpus_bleu(
            [[tokens(r)] for r in refs],
            [tokens(h) for h in hyps],
            weights=tuple([1 / n] * n),
            smoothing_function=SmoothingFunction().method1,
        )
        assert ours[f"bleu{n}"] == pytest.approx(want, abs=1e-12)
    sc = rouge_scorer.RougeScorer(["rougeL"], use_stemmer=True)
    want = sum(sc.score(r, h)["rougeL"].fmeasure for r, h in zip(refs, hyps)) / 2
    assert rouge_l(refs, hyps) == pytest.approx(want, abs=1e-12)
    assert bleu(refs, refs)["bleu4"] == pytest.approx(1.0) and rouge_l(refs, refs) == pytest.approx(1.0)


# free-form replies and what the parser reads from them, by dimension (in the order the cases run)
REPLIES = (
    ("Q2", [("Yes, the beaker slipped.", "Yes"), ("No.", "No"), ("Not at all, it went fine", "No")]),
    ("Q3", [("The failure occurs at frame 7.", "7"), ("None", "None"), ("¯\\_(ツ)_/¯", None)]),
    ("Q4", [("(2) Dangerous Level", "2"), ("Dangerous", "2"), ("Management Incident", "4")]),
    ("Q5", [("Grasping Failure", "2"), ("4", "4"), ("It is a motion failure.", "3"), ("", None)]),
    ("Q1", [("Grasping, then placing.", "grasp, place"), ("open, grasp, place, close", "open, grasp, place, close")]),
)


@pytest.mark.parametrize("dim,reply,want", [(dim, reply, want) for dim, cases in REPLIES for reply, want in cases])
def test_parse_free_form_replies(dim, reply, want):
    from labrobfail_vlm.bench.parse import parse

    assert parse(dim, reply) == want


def test_evaluate_model_and_predictions_file(tiny, small_ds, tmp_path):  # noqa: F811
    # labrobfail-evaluate in this process here (it runs as one in test_faults.py)
    r = evaluate(f"model={tiny}", small_ds, "split=test", f"out_dir={tmp_path / 'e'}", "progress=false", call=run_here)
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads((tmp_path / "e" / "results.json").read_text())
    for k in ("q1", "q2", "q3", "q4", "q5", "q3_within1"):
        assert 0 <= res[k] <= 100
    assert set(res["q6"]) == {"bleu1", "bleu2", "bleu3", "bleu4", "rougeL"}
    assert {"majority class", "blind (grey grid)"} <= set(res["baselines"])
    md = (tmp_path / "e" / "results.md").read_text()
    assert "| LabRobFail-VLM (paper) | 94.45" in md and "All-trajectory scores" in md and "AUROC" in md
    assert (tmp_path / "e" / "confusion_q2.png").is_file() and (tmp_path / "e" / "reliability_q2.png").is_file()
    fo, det = res["failure_only"], res["detection"]
    assert fo["trajectories"] > 0 and all(0 <= fo[k] <= 100 for k in ("q3", "q4", "q5"))
    assert det["score"] == "probability" and det["auroc"] is not None and 0 <= det["ece"] <= 1
    assert res["baselines"]["majority class"]["detection"]["auroc"] == 0.5  # a constant score ranks nothing
    # the same predictions, scored from the file they were saved to, give the same numbers
    saved = f"predictions={tmp_path / 'e' / 'predictions.jsonl'}"
    r = evaluate(saved, small_ds, f"out_dir={tmp_path / 'p'}", "baselines=[majority]", call=run_here)
    assert r.returncode == 0, r.stderr[-2000:]
    res2 = json.loads((tmp_path / "p" / "results.json").read_text())
    keys = ("q1", "q2", "q3", "q4", "q5", "q6", "failure_only")
    assert {k: res2[k] for k in keys} == {k: res[k] for k in keys}
    assert res2["detection"]["auroc"] == res["detection"]["auroc"]  # P(failure) travels in the predictions file
    (tmp_path / "bad.jsonl").write_text("{not json}\n")
    r = evaluate(f"predictions={tmp_path / 'bad.jsonl'}", small_ds, call=run_here)
    assert r.returncode == 2 and "line 1" in r.stderr and "Traceback" not in r.stderr
    # a missing model is refused before anything is written (no empty eval_<split> folder beside it)
    r = evaluate(f"model={tmp_path / 'gone' / 'final'}", small_ds, call=run_here)
    assert r.returncode == 2 and "no such directory" in r.stderr and not (tmp_path / "gone").exists()


def test_evaluate_on_the_first_trajectories_of_the_train_split(tiny, small_ds, tmp_path):  # noqa: F811
    # the fit diagnostic: the model on its own training data, cut to the split's first N trajectories
    from labrobfail_vlm import questions as Q

    model = tmp_path / "m"  # the tiny model, its bench folder written beside it here
    model.mkdir()
    for f in tiny.iterdir():
        (model / f.name).symlink_to(f)
    fast = ("baselines=[]", "q6_template=false", "progress=false")
    r = evaluate(f"model={model}", small_ds, "split=train", "max_trajectories=2", *fast, call=run_here)
    assert r.returncode == 0, r.stderr[-2000:]
    out = model / "eval_train_first2"  # named apart from a whole-split bench
    ids = [json.loads(line)["id"] for line in (out / "predictions.jsonl").read_text().splitlines()]
    train = json.loads((small_ds / "train.json").read_text())
    first = list(dict.fromkeys(Q.traj_of(r["id"]) for r in train))[:2]
    assert len(first) == 2 and sorted(ids) == sorted(r["id"] for r in train if Q.traj_of(r["id"]) in first)
    assert json.loads((out / "results.json").read_text())["failure_only"]["trajectories"] <= 2
    r = evaluate(f"model={tiny}", small_ds, "max_trajectories=0", call=run_here)
    assert r.returncode == 2 and "max_trajectories: expected a positive integer" in r.stderr
    # a sealed split is never benched in part (its ledger line would show a subset's figures as the split's)
    r = evaluate(f"model={tiny}", small_ds, "split=test_both", "max_trajectories=2", call=run_here)
    assert r.returncode == 2 and "test_both is a sealed split" in r.stderr.strip().splitlines()[-1]


def test_accuracy_threshold_is_the_best_cut_and_ties_go_to_one_half():
    from labrobfail_vlm.bench.detection import accuracy_threshold

    assert accuracy_threshold([False, False, True, True], [0.1, 0.6, 0.7, 0.9]) == pytest.approx(0.65)
    assert accuracy_threshold([True, True, False], [0.2, 0.3, 0.1]) == pytest.approx(0.15)
    assert accuracy_threshold([False, True], [0.2, 0.8]) == 0.5  # every cut between them is as good: the argmax
    assert accuracy_threshold([False, False], [0.3, 0.3]) == 0.5
    with pytest.raises(ValueError, match="no scored"):
        accuracy_threshold([], [])


def test_evaluate_at_the_operating_point_chosen_on_val(tiny, small_ds, tmp_path):  # noqa: F811
    from labrobfail_vlm.bench import evaluate as ev

    model = tmp_path / "m"  # the tiny model, with a seen-val bench of its own written below
    model.mkdir()
    for f in tiny.iterdir():
        (model / f.name).symlink_to(f)
    fast = ("split=test", "baselines=[]", "q6_template=false", "progress=false")
    for arg, needle in (
        ("threshold=val", "eval_val/predictions.jsonl not found"),
        ("threshold=1.5", "threshold: expected val or a number between 0 and 1"),
    ):
        r = evaluate(f"model={model}", small_ds, arg, *fast, call=run_here)
        assert r.returncode == 2 and needle in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    r = evaluate(f"predictions={tmp_path / 'x.jsonl'}", small_ds, "threshold=0.3", call=run_here)
    assert r.returncode == 2 and "only a local model's run" in r.stderr
    assert not [p for p in model.iterdir() if p.name.startswith("eval_test")]  # refused before writing
    _, val = ev.load_split(small_ds, "val")
    assert {i["success"] for i in val.values()} == {True, False}, "the fixture's val split needs both outcomes"
    lines = [{"id": f"{t}_Q2", "prediction": "", "p_failure": 0.1 if i["success"] else 0.3} for t, i in val.items()]
    (model / "eval_val").mkdir()
    (model / "eval_val" / "predictions.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
    r = evaluate(f"model={model}", small_ds, "threshold=val", *fast, call=run_here)
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads((model / "eval_test_opval" / "results.json").read_text())
    assert res["threshold"] == pytest.approx(0.2) and res["threshold_chosen_on"] == "val"
    recs, _ = ev.load_split(small_ds, "test")  # every verdict is P(failure) >= 0.2, whichever way Q2 is asked
    asked = {r["id"]: r["conversations"][0]["value"] for r in recs if r["id"].endswith("_Q2")}
    out = [json.loads(x) for x in (model / "eval_test_opval" / "predictions.jsonl").read_text().splitlines()]
    q2 = [x for x in out if x["id"] in asked]
    assert q2 and all(x["prediction"] == ev.q2_as_asked(asked[x["id"]], x["p_failure"] >= 0.2) for x in q2)
    # a sealed look at an operating point names it in the ledger (the same records asked as a sealed split)
    ds2 = tmp_path / "ds2"
    ds2.mkdir()
    for f in small_ds.iterdir():
        (ds2 / f.name).symlink_to(f)
    (ds2 / "test_both.json").symlink_to(small_ds / "test.json")
    r = evaluate(f"model={model}", ds2, "split=test_both", "threshold=val", *fast[1:], call=run_here)
    assert r.returncode == 0, r.stderr[-2000:]
    r = evaluate(f"model={model}", ds2, "split=test_both", "threshold=0.3", *fast[1:], call=run_here)
    assert r.returncode == 0, r.stderr[-2000:]
    assert [(e["split"], e["source"]) for e in ev.sealed_runs(ds2)] == [
        ("test_both", f"{model} at P(failure) >= 0.2 (chosen on val)"),
        ("test_both", f"{model} at P(failure) >= 0.3"),
    ]


def _q6_prefix(fa, img, task):
    prompts = {"Q6": fa._prompt("Q6", task)}
    return next(fa._prefixes(img, prompts))[1]


def test_q6_free_text_never_repeats_a_trigram(tiny, grid):  # noqa: F811
    from labrobfail_vlm.analyzer import FailureAnalyzer

    fa = FailureAnalyzer.from_pretrained(tiny)
    img = Image.open(grid).convert("RGB")
    d = fa.decoder
    d.max_new_tokens = 48

    def tokens(n):
        d.no_repeat_ngram = n
        return d.free_tokens(_q6_prefix(fa, img, "pick up the beaker"))

    def repeats(ids):
        grams = [tuple(ids[i : i + 3]) for i in range(len(ids) - 2)]
        return len(grams) - len(set(grams))

    assert repeats(tokens(0)) > 0  # an untrained model's greedy text loops ...
    assert repeats(tokens(3)) == 0  # ... the guard stops that


def test_score_many_equals_scoring_each_sequence_alone(tiny, grid):  # noqa: F811
    from labrobfail_vlm.analyzer import FailureAnalyzer

    fa = FailureAnalyzer.from_pretrained(tiny)
    pre = _q6_prefix(fa, Image.open(grid).convert("RGB"), "pick up the beaker")
    d = fa.decoder
    seqs = [
        d.encode_ids(t)
        for t in (
            "Move the robotic arm to the beaker",
            "Move the robotic arm to the flask",
            "Keep the gripper closed",
            "Move",
        )
    ]
    together = d.score_many(pre, seqs)
    for s, got in zip(seqs, together):
        _, logits = d.extend(pre, s)
        lps = torch.log_softmax(torch.cat([pre.last_logits[None], logits[:-1]]), -1)
        d.rewind(_, pre)
        assert got == pytest.approx(float(lps[torch.arange(len(s)), torch.tensor(s)].sum()), abs=1e-4)


def test_q6_template_mode_picks_a_filled_strategy(tiny, grid):  # noqa: F811
    from labrobfail_vlm.analyzer import FailureAnalyzer, nearest_strategy
    from labrobfail_vlm.corrections import candidates

    fa = FailureAnalyzer.from_pretrained(tiny, q6_mode="template")
    names = ["small beaker", "target area"]
    pre = _q6_prefix(fa, Image.open(grid).convert("RGB"), "pick up the small beaker")
    reply = fa._answer("Q6", pre, True, 8, names)
    cands = dict((text, sid) for sid, text in candidates(names))
    assert reply in cands and nearest_strategy(reply) == cands[reply]
    # ranked by mean log-likelihood per token (end of turn included), not by the sum, which favours short ones
    d, texts = fa.decoder, list(cands)
    seqs = [d.encode_ids(t) + [d.eos] for t in texts]
    lp = d.score_many(pre, seqs)
    assert reply == max(texts, key=lambda t: lp[texts.index(t)] / len(seqs[texts.index(t)]))
    assert d.choose_rows(pre, [texts], [False]) == [max(texts, key=lambda t: lp[texts.index(t)])]
    assert all("{" not in text for text in cands)  # every placeholder filled
    with pytest.raises(ValueError, match="q6_mode"):
        FailureAnalyzer.from_pretrained(tiny, q6_mode="beam")


def test_template_q6_follows_the_answered_category_and_severity(tiny, grid):  # noqa: F811
    """A template Q6 is chosen among the strategies the category Q5 gave and the severity Q4 gave admit (both are
    decoded for it even when only Q6 is asked), the same in one pass and six prompts; free Q6 asks neither."""
    from labrobfail_vlm.analyzer import FailureAnalyzer
    from labrobfail_vlm.corrections import candidates

    fa = FailureAnalyzer.from_pretrained(tiny, q6_mode="template", threshold=1e-6)  # every grid a failure
    names = ["small beaker", "target area"]
    img = Image.open(grid).convert("RGB")
    one = fa.answers(img, "pick up the small beaker", True, objects=names, dims={"Q6"})
    six = fa.answers(img, "pick up the small beaker", False, objects=names, dims={"Q6"})
    assert one == six and set(one) == {"Q2", "Q4", "Q5", "Q6"} and one["Q2"] == "Yes"
    narrowed = {t for _, t in candidates(names, int(one["Q5"]), int(one["Q4"]))}
    assert one["Q6"] in narrowed and len(narrowed) < len(candidates(names))
    fa.q6_mode = "free"
    assert set(fa.answers(img, "pick up the small beaker", True, objects=names, dims={"Q6"})) == {"Q2", "Q6"}


def test_evaluate_reports_types_template_row_and_skips_majority_without_train(tiny, small_ds, tmp_path):  # noqa: F811
    import shutil

    ds = tmp_path / "unseen_only"
    shutil.copytree(small_ds, ds)
    (ds / "train.json").unlink()
    r = evaluate(
        f"model={tiny}",
        ds,
        "split=test",
        f"out_dir={tmp_path / 'e'}",
        "progress=false",
        "baselines=[majority]",
        call=run_here,
    )
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert "majority baseline skipped" in r.stderr
    res = json.loads((tmp_path / "e" / "results.json").read_text())
    assert "majority class" not in res["baselines"]
    assert any(k.endswith("Q6 template") for k in res["baselines"])
    traj = json.loads((ds / "trajectories.json").read_text())
    types = {t["failure_type"] for t in traj if t["split"] == "test" and not t["success"]}
    assert {f"type:{t}" for t in types} <= set(res["breakdown"])


def test_failure_only_scores_a_none_for_every_failure_as_wrong(small_ds, tmp_path):  # noqa: F811
    """Gold Q1/Q2 and "None" / no correction for every Q3-Q6: the all-trajectory scores reward the successes'
    None answers, the failure-only scores (the paper's) give 0 on Q3-Q5 and a low ROUGE-L."""
    from labrobfail_vlm import questions as Q

    recs = json.loads((small_ds / "test.json").read_text())
    traj = {t["trajectory"]: t for t in json.loads((small_ds / "trajectories.json").read_text())}
    assert any(not traj[Q.traj_of(r["id"])]["success"] for r in recs)
    with open(tmp_path / "p.jsonl", "w") as f:
        for r in recs:
            d = Q.dim_of(r["id"])
            ans = r["conversations"][1]["value"] if d in ("Q1", "Q2") else Q.NO_CORRECTION if d == "Q6" else "None"
            f.write(json.dumps({"id": r["id"], "prediction": ans}) + "\n")
    r = evaluate(
        f"predictions={tmp_path / 'p.jsonl'}",
        small_ds,
        f"out_dir={tmp_path / 'e'}",
        "baselines=[majority]",
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads((tmp_path / "e" / "results.json").read_text())
    assert res["q1"] == 100 and res["q2"] == 100 and res["q3"] > 0 and res["q6"]["rougeL"] > 0.2
    fo = res["failure_only"]
    assert fo["q3"] == fo["q4"] == fo["q5"] == 0 and fo["q6"]["rougeL"] < 0.2
    assert res["detection"]["score"] == "hard" and res["detection"]["auroc"] == 1.0  # gold Q2 ranks perfectly
    maj = res["baselines"]["majority class"]["failure_only"]  # the training failures' most frequent answers
    assert maj["q4"] > 0 or maj["q5"] > 0


def test_detected_scores_the_diagnosis_of_the_failures_q2_caught(small_ds):  # noqa: F811
    """One failure missed by Q2 (and its Q3-Q5 answered None), every other answer gold: the failure-only scores
    count the miss as wrong, `detected` leaves it out and reads 100."""
    from labrobfail_vlm import questions as Q
    from labrobfail_vlm.bench import evaluate as ev

    recs, traj = ev.load_split(small_ds, "train")  # the fixture's split with the most failures
    failed = sorted({Q.traj_of(r["id"]) for r in ev.failed_records(recs, traj)})
    assert len(failed) >= 2, "the fixture's train split needs two failures"
    preds = {r["id"]: r["conversations"][1]["value"] for r in recs}
    for r in recs:
        if Q.traj_of(r["id"]) == failed[0]:
            d, q = Q.dim_of(r["id"]), r["conversations"][0]["value"]
            preds[r["id"]] = ev.q2_as_asked(q, failed=False) if d == "Q2" else preds[r["id"]] if d == "Q1" else "None"
    res = ev.score(recs, preds, traj)
    fo, det = res["failure_only"], res["failure_only"]["detected"]
    assert fo["trajectories"] == len(failed) and det["trajectories"] == len(failed) - 1
    assert fo["q4"] < 100 and det["q3"] == det["q4"] == det["q5"] == 100 and det["q6"]["rougeL"] == 1.0
    assert ev.called_failed(recs, preds) == set(failed[1:])


# ---- argument hygiene (issue 33): refused before inference, nothing left behind ------------------------------
def test_json_output_and_frame_count_are_checked_before_inference(tiny, tmp_path):  # noqa: F811
    import os

    Image.new("RGB", (256, 128), (9, 9, 9)).save(tmp_path / "g.png")
    (tmp_path / "out").mkdir()
    if os.geteuid() != 0:
        (tmp_path / "ro").mkdir(mode=0o555)
        unwritable = tmp_path / "ro" / "d.json"
    else:  # root writes through permission bits: /proc takes no new files, even from root
        unwritable = "/proc/labrobfail-d.json"
    before = sorted(p.name for p in tmp_path.iterdir())
    for args, needle in (
        (["--json", str(tmp_path / "out")], "is a directory"),
        (["--json", str(unwritable)], "cannot write"),
        (["--json", str(tmp_path / "nope" / "d.json")], "does not exist"),
        (["--num-frames", "0"], "num_frames:"),
    ):
        args = ["--grid", str(tmp_path / "g.png"), "--model", str(tiny), *args]
        r = infer(*args) if needle == "is a directory" else run_here(["infer.py", *args])  # the first as a process
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and needle in lines[0] and r.stdout == "", (args, r.stderr)
        assert "Loading weights" not in r.stderr  # refused before the model was loaded
    assert sorted(p.name for p in tmp_path.iterdir()) == before and not list((tmp_path / "out").iterdir())
    assert not list(tmp_path.rglob("*.tmp")) and not list(tmp_path.rglob("*.probe"))


def test_evaluate_refuses_a_predictions_folder_or_unreadable_file_before_writing(tmp_path):
    (tmp_path / "preds").mkdir()
    for pred, needle in (
        (tmp_path / "preds", "Is a directory"),
        (_unreadable(tmp_path), "cannot read"),
        (tmp_path / "missing.jsonl", "cannot read"),
    ):
        argv = [f"predictions={pred}", tmp_path / "ds"]
        r = evaluate(*argv, timeout=120) if needle == "Is a directory" else evaluate(*argv, call=run_here)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, (pred, r.stderr[-500:])
        assert lines[0].startswith("error: predictions: ") and str(pred) in lines[0] and needle in lines[0], lines
    assert not list((tmp_path / "preds").iterdir()) and not (tmp_path / "eval_test").exists()  # no output folder


def test_online_bench_calibrates_on_successes_and_scores_every_prefix(tiny, small_ds, tmp_path):  # noqa: F811
    out = tmp_path / "online"
    r = evaluate(
        f"model={tiny}", small_ds, "mode=online", "split=test", "calibration=train", f"out_dir={out}", call=run_here
    )
    assert r.returncode == 0, r.stderr[-2000:]
    from labrobfail_vlm.bench.online_alarm import bound_check

    res = json.loads((out / "online.json").read_text())
    # the robot-signal baseline is fitted on the train split: calibrated on it, its row is left out
    assert set(res["rows"]) == {"model", "majority class", "blind (grey grid)", "labeler on live state (ceiling)"}
    assert res["monitor"] is None  # no robot-signal row: no monitor saved
    ceiling = res["rows"]["labeler on live state (ceiling)"]
    assert ceiling["latency_s_median"] == 0.0 and "irreversible_failures" in ceiling
    assert "latency_s_median" in res["rows"]["model"]["0.2"]
    model = res["rows"]["model"]
    assert set(model) == {"0.01", "0.05", "0.1", "0.2"} and res["cpu_s_per_check"] > 0
    for row in model.values():
        assert row["false_alarm_rate"] is None or 0 <= row["false_alarm_rate"] <= 1
        assert row["n_calibration"] == res["calibration_successes"]
        if row["successes"]:  # the bound check, stored as the table reads it
            assert 0 <= row["bound_p"] <= 1 and row["bound_p"] == bound_check(row), row
    assert len(res["auroc_by_keyframe"]["model"]) >= 1 and (out / "auroc_by_keyframe.png").is_file()
    r = evaluate(f"model={tiny}", small_ds, "mode=online", "split=test", "calibration=test", call=run_here)
    assert r.returncode == 2 and "calibration: must be another split" in r.stderr, r.stderr
    # calibrated on another split than train, the robot-signal MLP (fitted on train) runs per grid frame and at every
    # trace sample; the small dataset has no val pair, so a copy names its test trajectories val as well (plumbing)
    from labrobfail_vlm.bench.online import DENSE, DENSE_EITHER, EITHER, LABELER, ROBOT, ROBOT_PAIR, pair_name

    ds = tmp_path / "ds"
    shutil.copytree(small_ds, ds)
    trajs = json.loads((ds / "trajectories.json").read_text())
    trajs += [{**t, "split": "val"} for t in trajs if t["split"] == "test" and "prefix_of" not in t]
    (ds / "trajectories.json").write_text(json.dumps(trajs))
    out = tmp_path / "online_val"
    online = [f"model={tiny}", ds, "mode=online", "split=test", "calibration=val"]
    r = evaluate(*online, f"out_dir={out}", "pair_shares=[0.2,0.5]", call=run_here)
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads((out / "online.json").read_text())
    assert {ROBOT, EITHER, DENSE, DENSE_EITHER, pair_name(0.2)} <= set(res["rows"]) and res["cpu_s_per_dense_check"] > 0
    assert len(res["rows"][DENSE_EITHER]["0.05"]["thresholds"]) == 2 and "latency_s_median" in res["rows"][DENSE]["0.2"]
    # the every-sample pair once per model's share of alpha, each with its own split and bound check
    for share in (0.2, 0.5):
        row = res["rows"][pair_name(share)]["0.1"]
        assert row["alphas"] == [0.1 * share, 0.1 * (1 - share)] and row["bound_p"] == bound_check(row)
    for bad in ("[0]", "[1.5]", "0.3", "[]", "[0.2,0.2]"):  # refused in one line before the model is loaded
        r = evaluate(*online, f"out_dir={tmp_path / 'bad'}", f"pair_shares={bad}", call=run_here)
        assert r.returncode == 2 and r.stderr.strip().splitlines()[-1].startswith("error: pair_shares:"), r.stderr
    assert not (tmp_path / "bad").exists()
    assert len(res["auroc_by_keyframe"][DENSE]) == len(res["auroc_by_keyframe"][ROBOT])
    assert DENSE in (out / "online.md").read_text()
    # the row to report, chosen on the calibration split among the alarms the bench scored (never the blind model)
    chosen = res["chosen_on_calibration"]
    assert set(chosen["candidates"]) == set(res["rows"]) - {"majority class", "blind (grey grid)", LABELER}
    assert chosen["chosen"] in chosen["candidates"] and f"**{chosen['chosen']}**" in (out / "online.md").read_text()
    # without a model: the robot-signal monitors, the majority class and the labeler, the same figures as beside it
    alone = tmp_path / "online_robot"
    argv = [cli("evaluate"), f"dataset_dir={ds}", "mode=online", "split=test", "calibration=val"]
    assert run_here([*argv, f"out_dir={alone}"]).returncode == 0
    robot = json.loads((alone / "online.json").read_text())
    assert list(robot["rows"]) == ["majority class", ROBOT, DENSE, ROBOT_PAIR, "labeler on live state (ceiling)"]
    # its robot-signal alarms saved for the supervisor: they sound where the bench says, read again from the files
    from test_monitor import reproduces_bench

    reproduces_bench(alone, ds, robot)
    # the two MLPs paired: either sounds, each at half of alpha, so at most the sum of their false alarms at alpha/2
    for a in ("0.1", "0.2"):
        row = robot["rows"][ROBOT_PAIR][a]
        assert row["alphas"] == [float(a) / 2] * 2 and row["bound_p"] == bound_check(row)
        assert row["detection_rate"] >= max(
            robot["rows"][m][str(float(a) / 2)]["detection_rate"] for m in (ROBOT, DENSE)
        )
    assert robot["rows"][DENSE] == res["rows"][DENSE] and robot["cpu_s_per_check"] is None
    r = run_here(argv)
    assert r.returncode == 2 and r.stderr.strip().splitlines()[-1].endswith(
        "give out_dir= (the robot-signal monitors alone)"
    )
    # training-conditional (delta): the same monitors at a rank at least as high, their rows and bound checks say so
    from labrobfail_vlm.alarm import conformal_rank

    pac = tmp_path / "online_pac"
    assert run_here([*argv, f"out_dir={pac}", "delta=0.2"]).returncode == 0
    tight = json.loads((pac / "online.json").read_text())
    for a in ("0.1", "0.2"):
        row, loose = tight["rows"][ROBOT][a], robot["rows"][ROBOT][a]
        assert row["delta"] == 0.2 and "delta" not in loose and row["bound_p"] == bound_check(row)
        assert row["threshold"] is None or loose["threshold"] is not None and row["threshold"] >= loose["threshold"]
        assert row["false_alarm_rate"] <= loose["false_alarm_rate"]
    n = tight["calibration_successes"]  # a handful (the rank's arithmetic is tests/test_alarm.py's): the plumbing
    for a, row in tight["rows"][ROBOT].items():
        assert (row["threshold"] is None) == (conformal_rank(n, float(a), 0.2) > n), (a, n)
    assert tight["delta"] == 0.2 and "probability 0.8" in (pac / "online.md").read_text()
    for bad in ("0", "1", "true", "x"):
        r = run_here([*argv, f"out_dir={tmp_path / 'bad'}", f"delta={bad}"])
        assert r.returncode == 2 and r.stderr.strip().splitlines()[-1].startswith("error: delta:"), r.stderr
    assert not (tmp_path / "bad").exists()
    # an online run on a sealed split, scored or calibrated on, is counted in the ledger like an offline one
    from labrobfail_vlm.bench.evaluate import sealed_runs

    trajs += [{**t, "split": "test_both"} for t in trajs if t["split"] == "test" and "prefix_of" not in t]
    (ds / "trajectories.json").write_text(json.dumps(trajs))
    assert sealed_runs(ds) == []  # the runs above scored test and calibrated on val
    for split, cal in (("test_both", "val"), ("test", "test_both")):
        assert (
            run_here([*argv[:3], f"split={split}", f"calibration={cal}", f"out_dir={tmp_path / split}"]).returncode == 0
        )
    runs = sealed_runs(ds)
    assert [(e["split"], e["source"]) for e in runs] == [
        ("test_both", "online, scored: robot-signal monitors"),
        ("test_both", "online, calibration: robot-signal monitors"),
    ]
    (ds / "robot_signals.parquet").write_bytes(b"not a parquet file")  # a damaged file: one line, nothing written
    r = run_here([*argv, f"out_dir={tmp_path / 'damaged'}"])
    last = r.stderr.strip().splitlines()[-1]
    assert (
        r.returncode == 2 and "cannot read" in last and "robot_signals.parquet" in last and "Traceback" not in r.stderr
    )
    assert not (tmp_path / "damaged" / "online.json").exists()


def test_robot_signal_baseline_reads_each_prefix_and_scores_held_out_trajectories(small_ds):  # noqa: F811
    from labrobfail_vlm.bench import robot_baseline

    trajs = [t for t in json.loads((small_ds / "trajectories.json").read_text()) if "prefix_of" not in t]
    for t in trajs:  # when each frame was taken, and the robot's signals per frame, from the shard's trace
        assert len(t["frame_times_s"]) == len(t["robot_signals"]) == t["frames"]
        assert t["frame_times_s"] == sorted(t["frame_times_s"]) and len(t["robot_signals"][0]) == 12
    sig = [[0.0] * 12 for _ in range(3)]
    sig[1][9], sig[2][9], sig[0][11] = 0.05, 0.01, 0.02
    f = robot_baseline.prefix_features(sig)
    assert f.shape == (3, 16)  # the frame's signals, the three running maxima, k / F
    assert f[:, 12].tolist() == [0.0, 0.05, 0.05] and f[:, 14].tolist() == [0.02, 0.02, 0.02]
    assert f[:, 15].tolist() == pytest.approx([1 / 3, 2 / 3, 1.0])
    train = [t for t in trajs if t["split"] == "train"]
    test = [t for t in trajs if t["split"] == "test"]
    scores = robot_baseline.score(robot_baseline.fit(train), test)
    assert [len(s) for s in scores] == [t["frames"] for t in test] and all(0 <= p <= 1 for s in scores for p in s)
    # every trace sample's signals (robot_signals.parquet): at each grid frame's time, the frame's signals
    tables = robot_baseline.read_dense(small_ds, [t["trajectory"] for t in trajs])
    for t in trajs:
        tab = tables[t["trajectory"]]
        assert tab.shape[1] == 14 and np.all(np.diff(tab[:, 0]) >= 0) and np.all(np.diff(tab[:, 1]) >= 0)
        at = np.searchsorted(np.round(tab[:, 0], 4), t["frame_times_s"])
        assert np.allclose(tab[at, 2:], t["robot_signals"], atol=2e-4), t["trajectory"]
    dense = robot_baseline.score_dense(robot_baseline.fit_dense(train, tables), test, tables)
    assert [len(d) for d in dense] == [len(tables[t["trajectory"]]) for t in test]
    assert robot_baseline.read_dense(small_ds, ["no-such-trajectory"]) is None
    # every row reads the past only: a trace cut at any sample gives the same features up to it
    tab = tables[test[0]["trajectory"]]
    whole = robot_baseline.dense_features(tab)
    for cut in (1, 2, len(tab) // 2, len(tab) - 1):
        assert np.allclose(robot_baseline.dense_features(tab[:cut]), whole[:cut]), cut


def test_a_score_on_a_bin_edge_falls_in_the_bin_it_opens() -> None:
    """ECE's ten bins are [0, 0.1), [0.1, 0.2), ...: a score of exactly 0.3, 0.6 or 0.7 opens its bin (the edges
    np.linspace makes are 0.30000000000000004, ... and put it one bin low)."""
    from labrobfail_vlm.bench.detection import detection_metrics

    bins = detection_metrics([True, False, False], [0.3, 0.6, 0.7])["bins"]
    assert [(b["lo"], b["n"]) for b in bins] == [(0.3, 1), (0.6, 1), (0.7, 1)]


def test_the_majority_class_of_whole_grids_is_taken_from_whole_trajectories() -> None:
    """A dataset built with prefix cuts trains on whole grids and prefix grids; a prefix of a failure before its onset
    answers "no failure yet", so counting it would move a whole grid's failure rate (and could flip its answer). A
    whole-grid split takes the whole trajectories' answers, a prefix split the prefixes'."""
    from labrobfail_vlm import questions as Q
    from labrobfail_vlm.bench.evaluate import majority_predictions, same_kind

    ask = Q.VARIANTS["Q2"][0].text  # "Is there any error ...?": "Yes" = failed

    def rec(t: str, failed: bool) -> dict:
        return {"id": f"{t}_Q2", "conversations": [{"value": ask}, {"value": "Yes" if failed else "No"}]}

    # two whole failures and a success; three prefixes of the failures, before their onset
    train = [rec("f1", True), rec("f2", True), rec("s1", False), *(rec(f"f1-p{k}", False) for k in range(3))]
    train_traj = {"f1": {}, "f2": {}, "s1": {}, **{f"f1-p{k}": {"prefix_of": "f1"} for k in range(3)}}
    whole, prefix = [rec("t1", False)], [rec("t1-p0", False)]
    traj = {"t1": {}, "t1-p0": {"prefix_of": "t1"}}
    kept = same_kind(train, train_traj, whole, traj)
    assert [r["id"] for r in kept] == ["f1_Q2", "f2_Q2", "s1_Q2"]
    got = majority_predictions(kept, whole)
    assert got["t1_Q2"] == "Yes" and abs(got.p_failure["t1"] - 2 / 3) < 1e-9  # all six records: "No", rate 1/3
    assert [r["id"] for r in same_kind(train, train_traj, prefix, traj)] == [f"f1-p{k}_Q2" for k in range(3)]
    assert same_kind(train[:3], train_traj, prefix, traj) == train[:3]  # no prefixes to learn from: every record


def _renamed(ds, split: str, prefixes: list[str], to: str, keep: bool = True) -> None:
    """Add to dataset `ds` copies of its `split` trajectories under new names and pairs (one per prefix, as if drawn
    apart), in split `to`, their robot-signal traces copied alike; `keep=False`: the copies alone remain."""
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    trajs = json.loads((ds / "trajectories.json").read_text())
    base = [t for t in trajs if t["split"] == split and "prefix_of" not in t]
    table = pq.read_table(ds / "robot_signals.parquet")
    mine = table.filter(pc.is_in(table["trajectory"], value_set=pa.array([t["trajectory"] for t in base])))
    at = table.schema.get_field_index("trajectory")
    copies = [
        mine.set_column(at, "trajectory", pa.array([p + n for n in mine.column("trajectory").to_pylist()]))
        for p in prefixes
    ]
    new = [
        {**t, "trajectory": p + t["trajectory"], "group": p + t["group"], "split": to} for p in prefixes for t in base
    ]
    for p in prefixes if (ds / "images").is_dir() else []:  # each copy's grid, for a model's bench
        for t in base:
            shutil.copyfile(ds / "images" / f"{t['trajectory']}.png", ds / "images" / f"{p}{t['trajectory']}.png")
    (ds / "trajectories.json").write_text(json.dumps([*(trajs if keep else []), *new]))
    pq.write_table(pa.concat_tables([*([table] if keep else []), *copies]), ds / "robot_signals.parquet")


def _renamed_copy(src, dst, split: str, to: str | None = None) -> None:
    """A dataset of `src`'s `split` trajectories alone, under new names and pairs (as if drawn apart), in split `to`
    (default: the same name)."""
    shutil.copytree(src, dst)
    _renamed(dst, split, ["apart-"], to or split, keep=False)


def test_online_bench_without_a_train_split_to_fit_on_says_so_in_one_line(small_ds, tmp_path):  # noqa: F811
    """A dataset built with no train split (an ACT's rollouts, ratios [0, 0.5, 0.5]), or one whose train split
    holds one outcome only: the robot-signal MLPs have nothing to fit, so without a model the bench refuses in one
    line (it failed inside numpy before); with one it runs the model's rows alone (not run here)."""
    for name, keep in (
        ("none", lambda t: {**t, "split": "val"} if t["split"] == "train" else t),
        ("one_outcome", lambda t: t if t["split"] != "train" or t["success"] else None),
    ):
        ds = tmp_path / name
        shutil.copytree(small_ds, ds)
        trajs = [keep(t) for t in json.loads((ds / "trajectories.json").read_text())]
        trajs += [{**t, "split": "val"} for t in trajs if t and t["split"] == "test" and "prefix_of" not in t]
        (ds / "trajectories.json").write_text(json.dumps([t for t in trajs if t]))
        argv = [cli("evaluate"), f"dataset_dir={ds}", "mode=online", "split=test", "calibration=val"]
        r = run_here([*argv, f"out_dir={tmp_path / (name + '_out')}"])
        last = r.stderr.strip().splitlines()[-1]
        assert r.returncode == 2 and "Traceback" not in r.stderr and "no prefixes of both outcomes" in last, r.stderr
    from labrobfail_vlm.bench import robot_baseline

    trajs = json.loads((small_ds / "trajectories.json").read_text())
    assert robot_baseline.fit([]) is None
    assert robot_baseline.fit([t for t in trajs if t["success"] and t.get("robot_signals")]) is None


def test_online_bench_scores_a_dataset_drawn_apart_with_the_fit_and_calibration_of_another(  # noqa: F811
    tiny,  # noqa: F811
    small_ds,  # noqa: F811
    tmp_path,
):
    from labrobfail_vlm.bench.online import DENSE, ROBOT

    ds = tmp_path / "ds"  # renamed copies of the train split calibrate (plumbing): the MLPs fit them closely, so
    shutil.copytree(small_ds, ds)  # their thresholds are low and the rows compared below do alarm
    _renamed(ds, "train", [f"cal{i}-" for i in range(4)], "val")
    apart = tmp_path / "apart"
    _renamed_copy(small_ds, apart, "test")
    argv = [cli("evaluate"), f"dataset_dir={ds}", "mode=online", "split=test", "calibration=val"]
    assert run_here([*argv, f"out_dir={tmp_path / 'here'}"]).returncode == 0
    r = run_here([*argv, f"scored_dataset={apart}", f"out_dir={tmp_path / 'there'}"])
    assert r.returncode == 0, r.stderr[-2000:]
    here, there = (json.loads((tmp_path / d / "online.json").read_text()) for d in ("here", "there"))
    # the same trajectories under other names: the MLPs fitted on ds's train split, calibrated on its val, read alike
    assert there["scored_dataset"] == str(apart) and "scored_dataset" not in here
    assert there["rows"] == here["rows"] and there["trajectories"] == here["trajectories"]
    assert any(r["detected"] or r["false_alarms"] for m in (ROBOT, DENSE) for r in here["rows"][m].values())
    assert "split test of apart, a dataset drawn apart" in (tmp_path / "there" / "online.md").read_text()
    # a block built all-train is scored too: none of its trajectories is the fit's (the fit is dataset_dir's train)
    as_train = tmp_path / "as_train"
    _renamed_copy(small_ds, as_train, "test", "train")
    r = run_here([*argv, "split=train", f"scored_dataset={as_train}", f"out_dir={tmp_path / 'as_train_out'}"])
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads((tmp_path / "as_train_out" / "online.json").read_text())["rows"] == here["rows"]
    # a model's bench of a split drawn apart reads that split's grids there, in a folder of its own beside the model
    # (never MODEL/eval_online_test, the model's bench of its own seen test)
    model = tmp_path / "model"
    shutil.copytree(tiny, model)
    r = run_here([*argv, f"model={model}", f"scored_dataset={apart}", "calibration=train"])
    assert r.returncode == 0, r.stderr[-2000:]
    ran = json.loads((model / "eval_online_test_apart" / "online.json").read_text())
    assert ran["scored_dataset"] == str(apart) and "model" in ran["rows"] and not (model / "eval_online_test").exists()
    for row in there["rows"][ROBOT].values():  # the counts the page's exact intervals are drawn from
        assert row["false_alarm_rate"] == round(row["false_alarms"] / row["successes"], 4)
        assert row["detection_rate"] == round(row["detected"] / row["failures"], 4)
    # refused in one line, nothing written: a scored dataset sharing a pair with dataset_dir, another grid, offline
    shared = tmp_path / "shared"
    shutil.copytree(small_ds, shared)
    other_grid = tmp_path / "other_grid"
    _renamed_copy(small_ds, other_grid, "test")
    stats = json.loads((other_grid / "stats.json").read_text())
    (other_grid / "stats.json").write_text(
        json.dumps({**stats, "grid": {**stats["grid"], "width": 2 * stats["grid"]["width"]}})
    )
    no_grid = tmp_path / "no_grid"
    _renamed_copy(small_ds, no_grid, "test")
    (no_grid / "stats.json").write_text(json.dumps({k: v for k, v in stats.items() if k != "grid"}))
    for scored, extra, needle in (
        (shared, [], "pairs are also in dataset_dir"),
        (other_grid, [], "another grid"),
        (no_grid, [], "names no grid"),
        (tmp_path / "missing", [], "cannot read the dataset"),
        (apart, ["mode=offline", "predictions=x.jsonl"], "mode=online only"),
    ):
        r = run_here([*argv, f"scored_dataset={scored}", f"out_dir={tmp_path / 'bad'}", *extra])
        assert r.stderr.strip(), (scored, r.returncode, r.stdout[-500:])
        last = r.stderr.strip().splitlines()[-1]
        assert r.returncode == 2 and last.startswith("error: scored_dataset:") and needle in last, r.stderr[-800:]
        assert "Traceback" not in r.stderr and not (tmp_path / "bad").exists()
