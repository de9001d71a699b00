"""Verdicts on the paper's ablation findings: effects with intervals, equivalence with a margin, runs matched on
CPU kind; each rule checked on numbers whose answer is known."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from gns_bench.report.verdict import CONTRADICTED, EQUIVALENCE_MARGIN, INCONCLUSIVE, NOT_RUN, REPRODUCED, effect, judge

STEPS = {"default": 10, "better": [[10, 1], [10, 5], [5, 1]]}
MINOR = {"default": 2, "no_effect": True}
DEFAULT = [1.0, 1.1, 0.9]  # log spread 0.1: a factor of ~1.65 either way is what one seed against these can show


def seeds(centre: float, spread: float = 0.05, n: int = 3) -> list[float]:
    """n errors spread evenly on a log scale around `centre` (geometric mean exactly `centre`)."""
    return list(centre * np.exp(np.linspace(-spread, spread, n)))


def test_a_large_effect_in_the_papers_direction_is_reproduced() -> None:
    verdict = judge({10: seeds(1.0), 5: seeds(2.0), 1: seeds(5.0)}, STEPS)
    assert verdict.verdict == REPRODUCED
    assert "10 vs 1: 0.2x [" in verdict.detail and "3 vs 3 seeds, Welch t" in verdict.detail


def test_a_large_effect_against_the_paper_is_contradicted() -> None:
    verdict = judge({10: seeds(1.0), 1: seeds(0.3)}, STEPS)
    assert verdict.verdict == CONTRADICTED
    assert "10 vs 1: 3.3x" in verdict.detail and "against the paper" in verdict.detail


def test_no_effect_gives_no_direction() -> None:
    # the same distribution on both arms: the interval spans 1
    verdict = judge({10: [1.0, 1.3, 0.8], 1: [1.1, 0.9, 1.25]}, STEPS)
    assert verdict.verdict == INCONCLUSIVE and "interval spans 1" in verdict.detail


def test_one_seed_against_three_uses_the_pooled_spread() -> None:
    # 1.3x worse on one seed: inside what three seeds spread by 0.1 allow, so no verdict
    assert judge({10: DEFAULT, 1: [1.3]}, STEPS).verdict == INCONCLUSIVE
    # 5x worse on one seed: beyond it
    far = judge({10: DEFAULT, 1: [5.0]}, STEPS)
    assert far.verdict == REPRODUCED and "3 vs 1 seeds, pooled t" in far.detail
    interval, method = effect(DEFAULT, [5.0])
    logs = np.log(DEFAULT)  # the pooled t interval by hand: the one-seed arm adds no spread
    se = logs.std(ddof=1) * math.sqrt(1 / 3 + 1)
    half = stats.t.ppf(0.975, 2) * se
    assert method == "pooled t"
    assert interval.high == pytest.approx(math.exp(logs.mean() - math.log(5.0) + half))
    # one seed a side: nothing to judge by
    assert judge({10: [1.0], 1: [5.0]}, STEPS).verdict == INCONCLUSIVE


def test_pairs_not_run_give_no_verdict_and_nan_is_not_a_seed() -> None:
    assert judge({10: DEFAULT, 7: [5.0]}, STEPS).verdict == NOT_RUN
    assert judge({10: [1.0, float("nan")], 1: [5.0]}, STEPS).verdict == INCONCLUSIVE  # one seed a side


def test_equivalence_needs_an_interval_inside_the_margin() -> None:
    # within 5% and tight: equivalent
    within = judge({2: seeds(1.0, 0.02), 1: seeds(1.05, 0.02), 3: seeds(0.97, 0.02)}, MINOR)
    assert within.verdict == REPRODUCED and "within the margin" in within.detail
    # the same means with a wide spread: the interval leaves the margin, so no claim of little difference
    wide = judge({2: seeds(1.0, 0.4), 1: seeds(1.05, 0.4)}, MINOR)
    assert wide.verdict == INCONCLUSIVE
    # a 3x effect: contradicted
    large = judge({2: seeds(1.0), 1: seeds(3.0)}, MINOR)
    assert large.verdict == CONTRADICTED and "beyond the margin" in large.detail
    # an effect just inside the margin with a tight spread is still equivalent; just outside it is not
    assert judge({2: seeds(1.0, 0.01), 1: seeds(EQUIVALENCE_MARGIN * 0.97, 0.01)}, MINOR).verdict == REPRODUCED
    assert judge({2: seeds(1.0, 0.01), 1: seeds(EQUIVALENCE_MARGIN * 1.03, 0.01)}, MINOR).verdict != REPRODUCED


def test_equivalence_is_never_drawn_from_one_seed() -> None:
    tight = seeds(1.0, 0.01)  # so tight that one more seed at the same error would pass the pooled test
    assert effect([1.0], tight, 0.9)[0].high < EQUIVALENCE_MARGIN
    verdict = judge({2: tight, 1: [1.0]}, MINOR)
    assert verdict.verdict == INCONCLUSIVE and "equivalence needs two a side" in verdict.detail


def test_runs_on_different_cpu_kinds_are_not_compared() -> None:
    errors = {10: seeds(1.0), 1: seeds(5.0)}
    apart = judge(errors, STEPS, kinds={10: ["amd"] * 3, 1: ["intel"] * 3})
    assert apart.verdict == INCONCLUSIVE and "different CPU kinds" in apart.detail
    # matched on hardware: only the runs on a kind both arms have count
    mixed = judge({10: [1.0, 1.05, 0.95, 0.3], 1: seeds(5.0)}, STEPS, kinds={10: ["intel"] * 3 + ["amd"],
                                                                                1: ["intel"] * 3})
    assert mixed.verdict == REPRODUCED and "3 vs 3 seeds" in mixed.detail
    assert "1 run(s) on another CPU kind left out" in mixed.detail


def test_category_values_match_exactly() -> None:
    sharing = {"default": False, "better": [[False, True]]}
    assert judge({False: seeds(1.0), True: seeds(3.0)}, sharing).verdict == REPRODUCED
    encoding = {"default": "relative", "better": [["relative", "absolute"]]}
    assert judge({"relative": seeds(1.0), "absolute": seeds(0.2)}, encoding).verdict == CONTRADICTED


def test_a_measure_where_more_is_better_is_judged_the_other_way_round() -> None:
    # rollout steps before a monitor's stop: M=10 running ~170 steps against M=1's ~60 is the paper's direction
    steps = {10: [170.0, 180.0, 160.0], 1: [60.0, 55.0, 65.0]}
    verdict = judge(steps, STEPS, "rollout steps before a stop", higher_is_better=True)
    assert verdict.verdict == REPRODUCED
    assert "rollout steps before a stop of the first over the second" in verdict.detail
    assert judge(steps, STEPS).verdict == CONTRADICTED  # the same numbers read as errors
