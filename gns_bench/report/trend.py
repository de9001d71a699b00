"""Where a learning curve goes: the step from which a diagnostic stays at its target, and a power law fitted to
an error against training steps with the budget it predicts for a reference value (the paper's Table 1 figure).

Pure functions of (step, value) points, as `train.eval_every` logs them (`curve/<metric>`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats


def holds_from(points: list[tuple[float, bool]]) -> float | None:
    """The first evaluated step from which the condition holds at every later point, the last included; None
    when it fails at the last point or there is none."""
    since = None
    for step, holds in sorted(points):
        since = (step if since is None else since) if holds else None
    return since


def settled_step(points: list[tuple[float, float]], target: float = 1.0, tolerance: float = 0.1) -> float | None:
    """The first evaluated step from which every later point lies within `tolerance` (relative) of `target`,
    the last point included; None when the last point is outside (not settled yet) or there is none."""
    return holds_from([(step, math.isfinite(value) and abs(value - target) <= tolerance * abs(target))
                       for step, value in points])


@dataclass(frozen=True)
class PowerLaw:
    """value = scale x steps^exponent, fitted by least squares in log-log over `points` points from `first_step`
    on; `exponent_interval` is its 95% t interval (None with fewer than 3 points)."""

    scale: float
    exponent: float
    exponent_interval: tuple[float, float] | None
    points: int
    first_step: float
    last_step: float

    def value_at(self, steps: float) -> float:
        return self.scale * steps ** self.exponent

    def steps_to_reach(self, value: float) -> float | None:
        """The steps at which the fitted line reaches `value`; None when the curve does not fall toward it
        (exponent >= 0, or its interval reaches 0: no trend to extrapolate) or it is reached already."""
        if self.exponent >= 0 or (self.exponent_interval is not None and self.exponent_interval[1] >= 0):
            return None
        steps = (value / self.scale) ** (1.0 / self.exponent)
        return steps if steps > self.last_step else None


def fit_power_law(points: list[tuple[float, float]], from_fraction: float = 0.5) -> PowerLaw | None:
    """A power law through the curve's later part: the points at steps >= `from_fraction` x the last step (the
    early transient left out), positive values only; None with fewer than 2 such points."""
    usable = sorted((s, v) for s, v in points if s > 0 and math.isfinite(v) and v > 0)
    if not usable:
        return None
    last = usable[-1][0]
    usable = [(s, v) for s, v in usable if s >= from_fraction * last]
    if len(usable) < 2:
        return None
    x, y = np.log([s for s, _ in usable]), np.log([v for _, v in usable])
    fit = stats.linregress(x, y)
    interval = None
    if len(usable) >= 3:
        half = stats.t.ppf(0.975, len(usable) - 2) * fit.stderr
        interval = (float(fit.slope - half), float(fit.slope + half))
    return PowerLaw(float(math.exp(fit.intercept)), float(fit.slope), interval, len(usable), usable[0][0], last)
