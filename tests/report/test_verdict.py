"""Verdicts on the paper's ablation findings, computed from numbers against the default's seed spread."""

from __future__ import annotations

import math

from gns_bench.report.verdict import NO_SPREAD, NOT_REPRODUCED, NOT_RUN, REPRODUCED, WITHIN_SPREAD, judge

STEPS = {"default": 10, "better": [[10, 1], [10, 5], [5, 1]]}
MINOR = {"default": 2, "no_effect": True}
DEFAULT = [1.0, 1.1, 0.9]  # sample std of log10 0.0436: band x1.22 either way


def test_a_clear_ordering_reproduces_the_paper() -> None:
    verdict = judge({10: DEFAULT, 5: [2.0], 1: [5.0]}, STEPS)
    assert verdict.verdict == REPRODUCED
    assert "10 vs 1: 0.2x" in verdict.detail  # the error at 10 is a fifth of that at 1


def test_a_reversed_pair_is_not_reproduced_and_a_small_gap_is_inconclusive() -> None:
    reversed_pair = judge({10: DEFAULT, 1: [0.5]}, STEPS)
    assert reversed_pair.verdict == NOT_REPRODUCED
    assert "10 vs 1: 2x (against the paper, beyond the band)" in reversed_pair.detail
    assert judge({10: DEFAULT, 1: [1.1]}, STEPS).verdict == WITHIN_SPREAD
    mixed = judge({10: DEFAULT, 5: [1.05], 1: [3.0]}, STEPS)  # two clear, 10 vs 5 within
    assert mixed.verdict == WITHIN_SPREAD
    assert "10 vs 5: 0.95x (within the band)" in mixed.detail  # the pair the verdict turns on, named as such
    assert "5 vs 1: 0.35x (as the paper, beyond the band)" in mixed.detail


def test_without_seeds_or_pairs_there_is_no_verdict() -> None:
    assert judge({10: [1.0], 1: [5.0]}, STEPS).verdict == NO_SPREAD
    assert judge({10: DEFAULT, 7: [5.0]}, STEPS).verdict == NOT_RUN
    assert judge({10: [1.0, float("nan")], 1: [5.0]}, STEPS).verdict == NO_SPREAD  # NaN is not a seed


def test_no_effect_axes_are_reproduced_within_the_band() -> None:
    assert judge({2: DEFAULT, 1: [1.05], 3: [0.95]}, MINOR).verdict == REPRODUCED
    verdict = judge({2: DEFAULT, 1: [2.0]}, MINOR)
    assert verdict.verdict == NOT_REPRODUCED and "1: 2x the default's error" in verdict.detail


def test_category_values_match_exactly() -> None:
    sharing = {"default": False, "better": [[False, True]]}
    assert judge({False: DEFAULT, True: [3.0]}, sharing).verdict == REPRODUCED
    encoding = {"default": "relative", "better": [["relative", "absolute"]]}
    assert judge({"relative": DEFAULT, "absolute": [0.2]}, encoding).verdict == NOT_REPRODUCED


def test_the_band_is_twice_the_sample_std_of_the_defaults_log_error() -> None:
    # log10 of DEFAULT: sample std 0.0436, so the band is 10 ** 0.0872 = x1.22 (population std: x1.18)
    assert "band: x1.2 either way" in judge({10: DEFAULT, 1: [5.0]}, STEPS).detail
    mean = sum(math.log10(v) for v in DEFAULT) / 3
    inside = 10 ** (mean + 0.085)  # beyond the population band (0.0712), inside the sample one (0.0872)
    assert judge({10: DEFAULT, 1: [inside]}, STEPS).verdict == WITHIN_SPREAD
    assert judge({10: DEFAULT, 1: [10 ** (mean + 0.09)]}, STEPS).verdict == REPRODUCED


def test_a_measure_where_more_is_better_is_judged_the_other_way_round() -> None:
    # rollout steps before a monitor's stop: M=10 running 170 steps against M=1's 60 is the paper's direction
    steps = {10: [170.0, 180.0, 160.0], 1: [60.0]}
    verdict = judge(steps, STEPS, "rollout steps before a stop", higher_is_better=True)
    assert verdict.verdict == REPRODUCED
    assert "10 vs 1: 2.8x (as the paper, beyond the band)" in verdict.detail
    assert "rollout steps before a stop of the first over the second" in verdict.detail
    # the same numbers read as errors (lower is better) go against the paper
    assert judge(steps, STEPS).verdict == NOT_REPRODUCED
    fewer = judge({10: [170.0, 180.0, 160.0], 1: [400.0]}, STEPS, "steps", higher_is_better=True)
    assert fewer.verdict == NOT_REPRODUCED and "10 vs 1: 0.42x (against the paper, beyond the band)" in fewer.detail
    assert judge({10: [170.0, 180.0, 160.0], 1: [168.0]}, STEPS, higher_is_better=True).verdict == WITHIN_SPREAD
    minor = judge({2: [170.0, 180.0, 160.0], 1: [60.0]}, MINOR, "steps", higher_is_better=True)
    assert minor.verdict == NOT_REPRODUCED and "1: 0.35x the default's steps" in minor.detail
