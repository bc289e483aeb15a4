"""Batched decoding: analyze_batch gives the answers of one grid at a time (both Q2 verdicts, both Q6 modes,
mixed sizes, frames lists), and the lockstep decoder ops equal their single-row versions."""

from dataclasses import asdict

import pytest
from PIL import Image
from serve_fixtures import TASKS, frame_lists, grids, mixed_model  # noqa: F401  (fixtures)


@pytest.fixture(scope="module")
def fa(mixed_model):  # noqa: F811
    from labrobfail_vlm.analyzer import FailureAnalyzer

    return FailureAnalyzer.from_pretrained(mixed_model)


@pytest.mark.parametrize("q6_mode", ["free", "template"])
def test_analyze_batch_equals_one_at_a_time(fa, grids, q6_mode):  # noqa: F811
    from labrobfail_vlm.analyzer import DiagnosisRequest

    fa.q6_mode = q6_mode
    objects = ["small beaker", "target area"]
    reqs = [DiagnosisRequest(g, TASKS[i % 3], 8, objects) for i, g in enumerate(grids)]
    reqs.append(DiagnosisRequest(frame_lists(5, frames=5), "stir the solution"))  # composed in the model's layout
    alone = [fa.analyze(r.grid, r.task, frames=r.frames, objects=r.objects) for r in reqs]
    assert {d.failure for d in alone} == {True, False}  # both paths: Q3-Q6 decoded for some rows only
    for max_batch in (None, 3):
        together = fa.analyze_batch(reqs, max_batch=max_batch)
        # P(failure) comes from float sums over padded rows: equal to rounding, the answers exactly
        assert [d.p_failure for d in together] == pytest.approx([d.p_failure for d in alone], abs=1e-4)
        assert [{**asdict(d), "p_failure": None} for d in together] == [{**asdict(d), "p_failure": None} for d in alone]
    fa.q6_mode = "free"


def test_prompt_ids_equal_the_processor_tokenization(fa, grids):  # noqa: F811
    d = fa.decoder
    for dim in ("Q1", "Q4", "Q6"):
        p = fa._prompt(dim, "pick up the small beaker")
        ref = fa.processor(text=[p], images=[grids[-1]], return_tensors="pt")
        n = int(ref["image_grid_thw"][0].prod()) // fa.processor.image_processor.merge_size**2
        assert d.prompt_ids(p, n) == ref["input_ids"][0].tolist()


def test_lockstep_decoder_ops_equal_single_rows(fa, grids):  # noqa: F811
    """Rows of one batch, each with its own candidates / activity, against each row decoded alone."""
    d = fa.decoder
    imgs = [grids[0], grids[3], grids[1]]
    tasks = ["pick up the small beaker", "press the red button", "insert the rod into the flask"]
    prompts = [fa._prompt("Q6", t) for t in tasks]
    px = fa.processor.image_processor(images=imgs, return_tensors="pt")
    n = (px["image_grid_thw"].prod(-1) // 4).tolist()
    batch = d.prefill_rows([d.prompt_ids(p, k) for p, k in zip(prompts, n)], px["pixel_values"], px["image_grid_thw"])
    singles = [next(fa._prefixes(img, {"Q6": p}))[1] for img, p in zip(imgs, prompts)]
    cands = [["Yes", "No"], [str(i) for i in range(1, 9)], None]
    assert d.choose_rows(batch, cands) == [d.choose(s, c) if c else None for s, c in zip(singles, cands)]
    assert d.actions_rows(batch, [True, False, True]) == [d.actions(singles[0]), None, d.actions(singles[2])]
    d.max_new_tokens = 24
    avoid = [("Yes", "No"), (), ("None",)]
    got = d.free_tokens_rows(batch, avoid, [True, True, True])
    assert got == [d.free_tokens(s, a) for s, a in zip(singles, avoid)]
    # a sub-batch on its own cache leaves the shared one as it was
    sub = d.select(batch, [2])
    assert d.choose_rows(sub, [["Yes", "No"]]) == [d.choose(singles[2], ["Yes", "No"])]
    assert d.choose_rows(batch, cands) == [d.choose(s, c) if c else None for s, c in zip(singles, cands)]
    d.max_new_tokens = 96


def test_analyze_batch_accepts_plain_images_and_checks_lengths(fa, grids):  # noqa: F811
    got = fa.analyze_batch([grids[3], Image.new("RGB", (256, 128), (255, 255, 255))])
    assert [g.failure for g in got] == [False, False]
    with pytest.raises(ValueError, match="differ in length"):
        fa.answers_batch(grids[:2], ["only one task"])
