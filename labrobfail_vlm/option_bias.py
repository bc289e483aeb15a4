"""Option priors for the closed failure-only questions (Q3 frame, Q4 severity, Q5 category), chosen on validation.

The constrained decoder answers a closed question with the option of highest log-likelihood, and a small model's
likelihoods carry the answer frequencies it was taught: on the bench the severity reply sat under the majority
class. A bias per option, added to the options' log-likelihoods before the argmax (a prior correction, as in
"calibrate before use"), is fitted on the model's own seen-val bench by `labrobfail-calibrate` and stored in the
checkpoint's labrobfail.json, so every local user of the checkpoint (bench, infer, serve, supervise) answers with
it; an endpoint (vLLM's structured choice) has no option scores and answers without. Q2 is not biased here: its
operating point is the analyzer's threshold. Q3's prior is fitted on whole-trajectory grids; on prefix grids (the
supervisor's, the online bench's) the frames' prior differs, so a Q3 bias is a choice to check there.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np

from labrobfail_vlm.taxonomy import Category, Severity

BIASED_DIMS = ("Q3", "Q4", "Q5")
OBJECTIVES = ("likelihood", "accuracy")


def option_count(dim: str, frames: int) -> int:
    """The options of a closed failure-only question: Q3's are the keyframes shown."""
    return {"Q3": frames, "Q4": len(Severity), "Q5": len(Category)}[dim]


def numbered_options(dim: str, frames: int) -> tuple[str, ...]:
    """A closed failure-only question's numbered replies, "1" .. its option count (what the model chooses among
    after a failure; with "None" before them, the replies P(failure) reads)."""
    return tuple(str(i) for i in range(1, option_count(dim, frames) + 1))


def check_option_bias(value: Any) -> dict[str, tuple[float, ...]]:
    """`value` as {dim: (bias of option 1, option 2, ...)} for dims of BIASED_DIMS; a one-line ValueError for
    anything else (another key, a non-list, a non-finite number, a Q4 or Q5 list of another length than its
    options, an empty Q3 list)."""
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise ValueError(f"option_bias: expected a mapping of {', '.join(BIASED_DIMS)} to lists, got {value!r}")
    out: dict[str, tuple[float, ...]] = {}
    for dim, bias in value.items():
        if dim not in BIASED_DIMS:
            raise ValueError(f"option_bias: expected keys among {', '.join(BIASED_DIMS)}, got {dim!r}")
        ok = isinstance(bias, (list, tuple)) and all(
            isinstance(b, (int, float)) and not isinstance(b, bool) and math.isfinite(b) for b in bias
        )
        if not ok:
            raise ValueError(f"option_bias.{dim}: expected a list of finite numbers, got {bias!r}")
        n = option_count(dim, 1) if dim != "Q3" else None
        if (n is not None and len(bias) != n) or not bias:
            raise ValueError(
                f"option_bias.{dim}: expected {n or 'at least 1'} numbers (one per option), got {len(bias)}"
            )
        out[dim] = tuple(float(b) for b in bias)
    return out


def biased_choice(scores: Sequence[float], bias: Sequence[float] = ()) -> int:
    """The index of the best option once `bias` is added (an option past the bias's end gets 0); a tie goes to the
    first, as the decoder's own argmax does."""
    total = [s + (bias[k] if k < len(bias) else 0.0) for k, s in enumerate(scores)]
    return max(range(len(total)), key=total.__getitem__)


def accuracy(scores: Sequence[Sequence[float]], gold: Sequence[int], bias: Sequence[float] = ()) -> float:
    """The share of rows whose biased choice is the gold option (0-based)."""
    return sum(biased_choice(s, bias) == g for s, g in zip(scores, gold)) / max(1, len(gold))


def _nll(bias: np.ndarray, groups: list[tuple[np.ndarray, np.ndarray]], n_rows: int, ridge: float):
    """Mean negative log-likelihood of the gold options under softmax(scores + bias), plus ridge/2 |bias|^2, and
    its gradient. Rows are grouped by their option count (Q3's follows the frames shown)."""
    loss, grad = 0.5 * ridge * float(bias @ bias), ridge * bias.copy()
    for s, g in groups:
        k = s.shape[1]
        z = s + bias[:k]
        z = z - z.max(1, keepdims=True)
        lse = np.log(np.exp(z).sum(1))
        loss -= float((z[np.arange(len(g)), g] - lse).sum()) / n_rows  # log-softmax: no log(0) on a far option
        p = np.exp(z - lse[:, None])
        p[np.arange(len(g)), g] -= 1.0
        grad[:k] += p.sum(0) / n_rows
    return loss, grad


def fit_bias(
    scores: Sequence[Sequence[float]],
    gold: Sequence[int],
    n: int,
    objective: str = "likelihood",
    ridge: float = 0.01,
) -> list[float]:
    """Biases for `n` options from rows of option scores and their gold option (0-based; rows whose gold is not
    among their options are skipped). `likelihood`: the biases that maximise the mean log-likelihood of the gold
    options (convex; `ridge` keeps an option never seen finite); `accuracy`: coordinate ascent on the share of
    right choices over a grid of biases in [-4, 4] (option 1's bias fixed at 0, a tie kept at the smaller bias).
    An option that no fitted row offers keeps 0, as an option past a bias's end does."""
    if objective not in OBJECTIVES:
        raise ValueError(f"objective: expected one of {', '.join(OBJECTIVES)}, got {objective!r}")
    rows = [(list(s), g) for s, g in zip(scores, gold) if 0 <= g < len(s) <= n]
    if not rows:
        return [0.0] * n
    if objective == "accuracy":
        return _fit_accuracy([s for s, _ in rows], [g for _, g in rows], n)
    from scipy.optimize import minimize

    by_k: dict[int, list[tuple[list[float], int]]] = {}
    for s, g in rows:
        by_k.setdefault(len(s), []).append((s, g))
    groups = [(np.array([s for s, _ in v]), np.array([g for _, g in v])) for v in by_k.values()]
    res = minimize(_nll, np.zeros(n), args=(groups, len(rows), ridge), jac=True, method="L-BFGS-B")
    if not res.success:
        raise ValueError(f"option bias: the likelihood fit did not converge ({res.message})")
    b = res.x - res.x[0]  # a shift common to every option changes no choice: option 1 at 0, as accuracy's
    offered = max(len(s) for s, _ in rows)
    return [round(float(v), 4) if k < offered else 0.0 for k, v in enumerate(b)]


def _fit_accuracy(scores: list[list[float]], gold: list[int], n: int, sweeps: int = 3) -> list[float]:
    grid = sorted(np.arange(-4.0, 4.0001, 0.25).round(2).tolist(), key=abs)  # ties keep the smaller bias
    bias = [0.0] * n
    for _ in range(sweeps):
        moved = False
        for k in range(1, n):
            best, best_acc = bias[k], accuracy(scores, gold, bias)
            for v in grid:
                acc = accuracy(scores, gold, bias[:k] + [v] + bias[k + 1 :])
                if acc > best_acc + 1e-12:
                    best, best_acc = v, acc
            moved |= best != bias[k]
            bias[k] = best
        if not moved:
            break
    return bias
