"""Intervals for comparisons over seeds: what a verdict states beside its estimate.

Errors are compared as ratios (ours over theirs) of geometric means over seeds, with Welch's t interval on the
logarithms: MSEs spread multiplicatively across seeds (one seed's rollout error can be several times another's
at small budgets), and a ratio's interval is then symmetric on a log axis. Means of a quantity near a known
value (a gravity ratio against 1) get Student's t interval. Both assume the seeds are independent draws; with
2-3 seeds a side the intervals are wide, and saying so is the point.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats


@dataclass(frozen=True)
class Interval:
    estimate: float
    low: float
    high: float
    level: float = 0.95

    def contains(self, value: float) -> bool:
        return self.low <= value <= self.high

    def text(self, digits: int = 3, suffix: str = "") -> str:
        """"0.82x [0.61, 1.10]": the estimate and its interval, `suffix` after each number."""
        if not math.isfinite(self.estimate):
            return "—"
        fmt = f"{{:.{digits}g}}{suffix}"
        if not (math.isfinite(self.low) and math.isfinite(self.high)):
            return f"{fmt.format(self.estimate)} (no interval: one value)"
        return f"{fmt.format(self.estimate)} [{fmt.format(self.low)}, {fmt.format(self.high)}]"


def _finite(values: Sequence[float]) -> np.ndarray:
    array = np.asarray(values, dtype=float)
    return array[np.isfinite(array)]


def mean_interval(values: Sequence[float], level: float = 0.95) -> Interval:
    """The mean with Student's t interval; one value gives an unbounded interval, none gives NaN."""
    x = _finite(values)
    if len(x) == 0:
        return Interval(math.nan, math.nan, math.nan, level)
    mean = float(x.mean())
    if len(x) == 1:
        return Interval(mean, -math.inf, math.inf, level)
    half = float(stats.t.ppf(0.5 + level / 2, len(x) - 1) * x.std(ddof=1) / math.sqrt(len(x)))
    return Interval(mean, mean - half, mean + half, level)


def ratio_interval(ours: Sequence[float], theirs: Sequence[float], level: float = 0.95) -> Interval:
    """Geometric mean of `ours` over that of `theirs` (positive values, e.g. MSEs over seeds), with Welch's t
    interval of the difference of mean logarithms, exponentiated. Fewer than 2 values a side: unbounded."""
    a, b = np.log(_finite(ours)), np.log(_finite(theirs))
    if len(a) == 0 or len(b) == 0:
        return Interval(math.nan, math.nan, math.nan, level)
    estimate = float(np.exp(a.mean() - b.mean()))
    if len(a) < 2 or len(b) < 2:
        return Interval(estimate, 0.0, math.inf, level)
    va, vb = a.var(ddof=1) / len(a), b.var(ddof=1) / len(b)
    se = math.sqrt(va + vb)
    if se == 0.0:
        return Interval(estimate, estimate, estimate, level)
    df = (va + vb) ** 2 / (va**2 / (len(a) - 1) + vb**2 / (len(b) - 1))  # Welch-Satterthwaite
    half = float(stats.t.ppf(0.5 + level / 2, df) * se)
    diff = float(a.mean() - b.mean())
    return Interval(estimate, math.exp(diff - half), math.exp(diff + half), level)
