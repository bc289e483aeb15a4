"""Bench metrics: top-1 accuracy (Q1-Q5), Q3 within one frame, and BLEU-1..4 / ROUGE-L for Q6.

BLEU: nltk's corpus_bleu with cumulative uniform weights up to n and SmoothingFunction().method1
(fixed), on lower-cased word/punctuation tokens. ROUGE-L: rouge-score's RougeScorer with the
Porter stemmer, mean F-measure. Both are the reference implementations, called as they are.
95 % intervals: a percentile bootstrap over pairs (`pair_bootstrap`: a pair's twins are drawn together).
"""

from __future__ import annotations

import re
from typing import Sequence

import numpy as np
from nltk.translate.bleu_score import SmoothingFunction, corpus_bleu
from rouge_score import rouge_scorer

_TOKEN = re.compile(r"\w+|[^\w\s]")


def tokens(text: str) -> list[str]:
    return _TOKEN.findall(text.lower())


def bleu(refs: Sequence[str], hyps: Sequence[str]) -> dict[str, float]:
    if not refs:  # a split or prediction file without Q6 records (nltk divides by zero there)
        return {f"bleu{n}": 0.0 for n in range(1, 5)}
    r = [[tokens(x)] for x in refs]
    h = [tokens(x) for x in hyps]
    smooth = SmoothingFunction().method1
    return {
        f"bleu{n}": float(corpus_bleu(r, h, weights=tuple([1.0 / n] * n), smoothing_function=smooth))
        for n in range(1, 5)
    }


def rouge_l_values(refs: Sequence[str], hyps: Sequence[str]) -> list[float]:
    sc = rouge_scorer.RougeScorer(["rougeL"], use_stemmer=True)
    return [sc.score(r, h)["rougeL"].fmeasure for r, h in zip(refs, hyps)]


def rouge_l(refs: Sequence[str], hyps: Sequence[str]) -> float:
    vals = rouge_l_values(refs, hyps)
    return float(sum(vals) / len(vals)) if vals else 0.0


def pair_bootstrap(
    values: Sequence[float], groups: Sequence[str], resamples: int = 1000, seed: int = 0
) -> tuple[float, float] | None:
    """95 % percentile bootstrap interval of a mean whose samples come in groups (a success/failure pair's two
    twins share an initial state, so they are not independent): whole groups are drawn with replacement and the
    statistic is the mean over the values of the groups drawn. Seeded: the same scores give the same interval.
    With one value per group it is the ordinary bootstrap of the mean."""
    if not values:
        return None
    if len(values) != len(groups):
        raise ValueError(f"pair_bootstrap: {len(values)} values but {len(groups)} groups")
    names, idx = np.unique(np.asarray(groups, dtype=object).astype(str), return_inverse=True)
    sums = np.bincount(idx, weights=np.asarray(values, float), minlength=len(names))
    counts = np.bincount(idx, minlength=len(names)).astype(float)
    drawn = group_draws(len(names), resamples, seed)
    stats = (drawn @ sums) / (drawn @ counts)
    return float(np.percentile(stats, 2.5)), float(np.percentile(stats, 97.5))


def group_draws(n_groups: int, resamples: int = 1000, seed: int = 0) -> np.ndarray:
    """A resamples x n_groups matrix: how often each group is drawn in each bootstrap resample (n_groups draws with
    replacement). Scoring two models on the same matrix pairs their intervals (bench/compare.py)."""
    draw = np.random.default_rng(seed).integers(0, n_groups, (resamples, n_groups))
    flat = (draw + n_groups * np.arange(resamples)[:, None]).ravel()  # each resample's draws in a block of its own
    return np.bincount(flat, minlength=resamples * n_groups).reshape(resamples, n_groups).astype(float)


def accuracy(pairs: Sequence[tuple[str | None, str]]) -> float:
    return float(sum(p == r for p, r in pairs) / len(pairs)) if pairs else 0.0


def within_one(pairs: Sequence[tuple[str | None, str]]) -> float:
    ok = 0
    for p, r in pairs:
        if p is not None and p.isdigit() and r.isdigit():
            ok += abs(int(p) - int(r)) <= 1
        else:
            ok += p == r
    return float(ok / len(pairs)) if pairs else 0.0
