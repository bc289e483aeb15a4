"""Paired statistics of the recovery table: each trial runs twice from the same seed, without the supervisor and
with it, so the two success rates are compared on discordant pairs (McNemar), not as independent proportions.

Of n paired trials, `b` succeed without the supervisor and fail with it (successes it broke) and `c` fail without
and succeed with it (failures it rescued). The gain is (c - b) / n; its exact two-sided McNemar p is the binomial
test of b against b + c trials at 1/2 (scipy.stats.binomtest); its 95 % interval is Agresti and Min's (2005)
adjusted Wald interval for a paired difference (0.5 added to each of the four cells), which keeps its coverage for
the small discordant counts a recovery cell has.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Sequence

Z95 = 1.959963984540054


@dataclass(frozen=True)
class PairedCell:
    """One cell of the recovery table: n trials, each run without and with the supervisor from the same seed."""

    n: int
    base_successes: int
    supervised_successes: int
    broken: int  # b: succeeded without, failed with
    rescued: int  # c: failed without, succeeded with

    @property
    def gain(self) -> float:
        return (self.rescued - self.broken) / self.n

    @property
    def broken_share(self) -> float | None:
        """Of the trials that succeed without a supervisor, the share it broke (None when none succeeds: nothing
        to break, which is no 0 % either)."""
        return self.broken / self.base_successes if self.base_successes else None

    def summary(self) -> dict[str, Any]:
        lo, hi = difference_ci(self.broken, self.rescued, self.n)
        return asdict(self) | {
            "gain_points": round(100 * self.gain, 2),
            "ci95_points": [round(100 * lo, 2), round(100 * hi, 2)],
            "mcnemar_p": mcnemar_exact(self.broken, self.rescued),
            "broken_share": None if self.broken_share is None else round(self.broken_share, 4),
        }


def paired_cell(without: Sequence[bool], with_supervisor: Sequence[bool]) -> PairedCell:
    """The cell of two outcome lists, trial i of each run from the same seed."""
    if len(without) != len(with_supervisor) or not without:
        raise ValueError("paired: need the same, non-zero number of trials with and without the supervisor")
    pairs = list(zip(map(bool, without), map(bool, with_supervisor)))
    return PairedCell(
        n=len(pairs),
        base_successes=sum(a for a, _ in pairs),
        supervised_successes=sum(b for _, b in pairs),
        broken=sum(a and not b for a, b in pairs),
        rescued=sum(b and not a for a, b in pairs),
    )


def mcnemar_exact(b: int, c: int) -> float:
    """The exact two-sided McNemar p: 1.0 when there is no discordant pair."""
    if b + c == 0:
        return 1.0
    from scipy.stats import binomtest

    return float(binomtest(b, b + c, 0.5, alternative="two-sided").pvalue)


def difference_ci(b: int, c: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Agresti-Min interval of (c - b) / n, clipped to [-1, 1]."""
    if n <= 0 or b < 0 or c < 0 or b + c > n:
        raise ValueError(f"paired: need 0 <= b + c <= n and n > 0, got b={b}, c={c}, n={n}")
    b2, c2, n2 = b + 0.5, c + 0.5, n + 2.0
    d = (c2 - b2) / n2
    se = math.sqrt(max(0.0, (b2 + c2) - (c2 - b2) ** 2 / n2)) / n2
    return max(-1.0, d - z * se), min(1.0, d + z * se)


def paired_md(p: dict[str, Any] | None) -> str:
    """A cell's paired statistics as table columns: the gain's 95 % interval, McNemar's p, the broken successes."""
    if not p:
        return "- | - | -"
    lo, hi = p["ci95_points"]
    return f"[{lo:+.1f}, {hi:+.1f}] | {p['mcnemar_p']:.3g} | {p['broken']}/{p['base_successes']}"
