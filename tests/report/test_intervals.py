"""Intervals over seeds (gns_bench/report/intervals.py) against scipy's own t tests and closed forms."""

import math

import numpy as np
import pytest
from scipy import stats

from gns_bench.report.intervals import mean_interval, ratio_interval


def test_ratio_interval_is_welch_on_logarithms():
    ours, theirs = [2.0e-3, 3.1e-3, 2.6e-3], [4.0e-3, 9.0e-3, 5.5e-3]
    got = ratio_interval(ours, theirs)
    reference = stats.ttest_ind(np.log(ours), np.log(theirs), equal_var=False).confidence_interval(0.95)
    assert got.low == pytest.approx(math.exp(reference.low), rel=1e-9)
    assert got.high == pytest.approx(math.exp(reference.high), rel=1e-9)
    geometric = stats.gmean(ours) / stats.gmean(theirs)
    assert got.estimate == pytest.approx(geometric, rel=1e-12)
    assert got.low < got.estimate < got.high


def test_ratio_interval_scales_and_flips():
    ours, theirs = [1.0, 1.5, 1.2], [2.0, 2.2, 3.5]
    got = ratio_interval(ours, theirs)
    scaled = ratio_interval([10 * v for v in ours], theirs)  # 10x our error: 10x the ratio and its ends
    assert scaled.estimate == pytest.approx(10 * got.estimate)
    assert (scaled.low, scaled.high) == pytest.approx((10 * got.low, 10 * got.high))
    flipped = ratio_interval(theirs, ours)  # the other way round: reciprocal ends
    assert (flipped.low, flipped.high) == pytest.approx((1 / got.high, 1 / got.low))


def test_one_seed_a_side_is_unbounded():
    got = ratio_interval([1.0], [2.0, 3.0])
    assert got.estimate == pytest.approx(1 / math.sqrt(6.0))
    assert got.high == math.inf and got.contains(1.0)
    assert got.text(2, "x") == "0.41x (no interval: one value)"  # never "[0, inf]" in a table
    assert ratio_interval([1.0, 1.1], [2.0, 3.0]).text(2, "x").endswith("]")


def test_mean_interval_is_students_t():
    values = [0.91, 1.07, 0.98, 1.12]
    got = mean_interval(values)
    reference = stats.t.interval(0.95, len(values) - 1, loc=np.mean(values), scale=stats.sem(values))
    assert (got.low, got.high) == pytest.approx(reference, rel=1e-12)
    assert not mean_interval([1.5, 1.6, 1.55]).contains(1.0)  # clearly off 1: the interval says so


def test_nan_values_are_left_out():
    assert mean_interval([1.0, float("nan"), 2.0]).estimate == pytest.approx(1.5)
    assert math.isnan(mean_interval([float("nan")]).estimate)
