"""How the analyzer reads P(failure) from the model: the `failure_score` setting of FailureAnalyzer and of a
checkpoint's labrobfail.json.

"q2" (the default): Q2's own P("Yes") against "No". "questions": the mean of that and, for each closed failure-only
question (Q3, Q4, Q5), 1 - P("None") among "None" and its numbered options. The model is taught "None" as the Q3-Q5
reply to every successful grid, so these are three more detectors of the same grid under other wording.
"wordings": the same mean over every wording of Q2-Q5 the model was taught (questions.VARIANTS: 18 reads), a Q2
wording that asks whether the task succeeded read as its P("No"). Each probability is the constrained decoder's
softmax over whole replies (`Decoder.option_scores_rows`); nothing is fitted.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from labrobfail_vlm import questions as Q
from labrobfail_vlm.option_bias import numbered_options

FAILURE_SCORES = ("q2", "questions", "wordings")
SCORE_DIMS = ("Q3", "Q4", "Q5")
Q2_OPTIONS = ("Yes", "No")  # the admissible Q2 replies, "Yes" (a failure, in the first wording) first


def check_failure_score(value: Any) -> str:
    if value not in FAILURE_SCORES:
        raise ValueError(f"failure_score: expected one of {', '.join(FAILURE_SCORES)}, got {value!r}")
    return str(value)


def _softmax(scores: Sequence[float]) -> np.ndarray:
    z = np.asarray(scores, dtype=np.float64)
    e = np.exp(z - z.max())
    return e / e.sum()


def p_yes(options: Sequence[str], scores: Sequence[float]) -> float:
    """Softmax probability of "Yes" among the scored Yes/No replies."""
    return float(_softmax(scores)[list(options).index("Yes")])


def p_not_none(scores: Sequence[float]) -> float:
    """1 - softmax probability of the first scored reply ("None") among "None" and the numbered options."""
    return float(1.0 - _softmax(scores)[0])


def score_reads(failure_score: str, index: bool = True) -> tuple[tuple[str, str, int], ...]:
    """The question reads P(failure) averages under `failure_score`: (key, dimension, wording); the first wording's
    key is the dimension itself (the prompt its reply is asked with), another's "<dim>#<wording>". `index`: whether
    the grid draws frame numbers (Q3's wordings differ)."""
    dims = ("Q2",) if failure_score == "q2" else ("Q2", *SCORE_DIMS)
    n = {d: len(Q.variants(d, index)) if failure_score == "wordings" else 1 for d in dims}
    return tuple((d if v == 0 else f"{d}#{v}", d, v) for d in dims for v in range(n[d]))


def read_rows(decoder: Any, dim: str, pre: Any, frames: Sequence[int], variant: int = 0) -> list[float]:
    """Per row of `pre` (the model after `dim`'s prompt in wording `variant`; `frames`: each row's keyframes shown):
    P(failure) by that question alone."""
    if dim == "Q2":
        ps = [p_yes(Q2_OPTIONS, sc) for sc in decoder.option_scores_rows(pre, [Q2_OPTIONS] * len(frames))]
        return [1.0 - p for p in ps] if Q.VARIANTS["Q2"][variant].positive else ps
    opts = [(Q.NO_FAILURE, *numbered_options(dim, f)) for f in frames]
    return [p_not_none(sc) for sc in decoder.option_scores_rows(pre, opts)]


def shared_rows(
    decoder: Any,
    base: Any,
    ids: Sequence[dict[str, list[int]]],
    lcp: Sequence[int],
    frames: Sequence[int],
    reads: Sequence[tuple[str, str, int]],
) -> list[float]:
    """P(failure) for each row of `base` (the rows' shared preamble; `ids[i][key]` a row's prompt tokens, of which
    the first `lcp[i]` are in `base`): each read's question fed in turn and rewound, the reads averaged."""
    per_read = []
    for key, dim, v in reads:
        q, _ = decoder.extend_rows(base, [x[key][k:] for x, k in zip(ids, lcp)])
        per_read.append(read_rows(decoder, dim, q, frames, v))
        decoder.rewind(q, base)
    return [float(np.mean(col)) for col in zip(*per_read)]


def verdicts(probs: Sequence[float], threshold: float) -> list[str]:
    """Q2's reply at the operating point for each P(failure). At 0.5 with Q2 alone the reply is the argmax the
    constrained decoder's `choose_rows` picks (a tie goes to "Yes", its first option, in both)."""
    return ["Yes" if p >= threshold else "No" for p in probs]
