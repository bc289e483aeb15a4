"""Bench metrics: top-1 accuracy (Q1-Q5), Q3 within one frame, and BLEU-1..4 / ROUGE-L for Q6.

BLEU: nltk's corpus_bleu with cumulative uniform weights up to n and SmoothingFunction().method1
(fixed), on lower-cased word/punctuation tokens. ROUGE-L: rouge-score's RougeScorer with the
Porter stemmer, mean F-measure. Both are the reference implementations, called as they are.
"""

from __future__ import annotations

import math
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


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float] | None:
    """95 % Wilson score interval of a proportion k / n (None for n = 0): unlike the normal approximation it
    stays inside [0, 1] and is honest near 0 % and 100 %, which a 120-grid split reaches."""
    if n == 0:
        return None
    p, z2 = k / n, z * z
    mid, half = (p + z2 / (2 * n)) / (1 + z2 / n), z * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    return max(0.0, mid - half), min(1.0, mid + half)


def bootstrap_mean(values: Sequence[float], resamples: int = 1000, seed: int = 0) -> tuple[float, float] | None:
    """95 % percentile bootstrap interval of a mean (seeded: the same scores give the same interval)."""
    if not values:
        return None
    v = np.asarray(values, float)
    means = v[np.random.default_rng(seed).integers(0, len(v), (resamples, len(v)))].mean(1)
    return float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


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
    draw = np.random.default_rng(seed).integers(0, len(names), (resamples, len(names)))
    stats = sums[draw].sum(1) / counts[draw].sum(1)
    return float(np.percentile(stats, 2.5)), float(np.percentile(stats, 97.5))


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
