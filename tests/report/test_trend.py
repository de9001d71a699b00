"""Where a learning curve goes (report/trend.py): closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gns_bench.report.trend import fit_power_law, settled_step


def test_settled_step_is_where_the_curve_stays_within_the_band() -> None:
    curve = [(0, -2.0), (2000, 0.95), (4000, 1.3), (6000, 1.05), (8000, 0.98)]
    assert settled_step(curve) == 6000  # 0.95 at 2,000 left the band at 4,000
    assert settled_step(curve, tolerance=0.35) == 2000
    assert settled_step([*curve, (10000, 0.5)]) is None  # the last point is outside: not settled
    assert settled_step([(0, 1.0), (5, float("nan"))]) is None  # a NaN point is not within the band
    assert settled_step([]) is None
    assert settled_step(list(reversed(curve))) == 6000  # by step, whatever the order given


def test_a_power_law_is_recovered_and_extrapolated() -> None:
    steps = np.array([1000, 2000, 4000, 8000, 16000, 32000])
    exact = [(float(s), 3e-5 * s ** -0.5) for s in steps]
    fit = fit_power_law(exact, from_fraction=0.0)
    assert fit.exponent == pytest.approx(-0.5) and fit.scale == pytest.approx(3e-5)
    assert fit.points == 6 and fit.exponent_interval[0] == pytest.approx(-0.5)
    assert fit.steps_to_reach(3e-5 * 1e6 ** -0.5) == pytest.approx(1e6)
    assert fit.steps_to_reach(1.0) is None  # reached already
    late = fit_power_law(exact)  # from half the last step: 16,000 and 32,000
    assert late.points == 2 and late.exponent_interval is None and late.first_step == 16000

    rng = np.random.default_rng(0)
    noisy = [(float(s), 3e-5 * s ** -0.5 * math.exp(rng.normal(0, 0.1))) for s in steps]
    fit = fit_power_law(noisy, from_fraction=0.0)
    low, high = fit.exponent_interval
    assert low < -0.5 < high and high < 0 and fit.steps_to_reach(1e-9) > 32000


def test_a_flat_curve_predicts_nothing() -> None:
    rng = np.random.default_rng(1)
    flat = [(float(s), 9e-9 * math.exp(rng.normal(0, 0.2))) for s in range(2000, 22000, 2000)]
    fit = fit_power_law(flat)
    assert fit.exponent_interval[0] < 0 < fit.exponent_interval[1]
    assert fit.steps_to_reach(1.5e-9) is None
    assert fit_power_law([(0, 1.0), (10, -1.0)]) is None  # nothing positive at a positive step
