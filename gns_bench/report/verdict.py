"""Whether an ablation reproduces the paper's finding on its axis, computed from the runs.

The error compared is the rollout MSE divided by constant velocity's over the same steps, on a log scale:
like for like even when health monitors stopped rollouts at different steps, and on whole rollouts simply
the rollout MSE rescaled by one number per test set. Differences are judged against the seed spread at the
paper's default value (the campaign trains it with several seeds): the band is twice the sample standard
deviation (n - 1) of the log error over those seeds. A difference beyond the band counts; one inside it does not.

- `better = [[a, b], ...]` (the paper found a better than b): *reproduced* when every pair that was run has a
  below b beyond the band, *not reproduced* when some pair has a above b beyond it, else *inconclusive (within
  the seed spread)*.
- `no_effect = true` (App. C.1's minor axes): *reproduced* when every value stays within the band of the
  default, else *not reproduced*.
Without at least two finished seeds at the default there is no band: *inconclusive (no seed spread yet)*.

The same rules judge any positive measure of the runs on a log scale; `higher_is_better` flips the direction
for one where more is better, such as the number of rollout steps before a health monitor's stop, which the
error above cannot see (a rollout that collapses early is compared over its own few steps), or the one-step
MSE where Sec. 5.4 states a direction for it (`one_step_better`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from gns_bench.report.cells import any_stopped, relative_to_cv
from gns_bench.report.collect import RunRow

REPRODUCED = "the paper's direction reproduced"
NOT_REPRODUCED = "not reproduced"
WITHIN_SPREAD = "inconclusive (within the seed spread)"
NO_SPREAD = "inconclusive (no seed spread yet)"
NOT_RUN = "inconclusive (the values the paper compares were not run)"
PAIR_WORDS = {"yes": "as the paper, beyond the band", "no": "against the paper, beyond the band",
              "tie": "within the band"}


@dataclass(frozen=True)
class Verdict:
    verdict: str
    detail: str  # the comparisons behind it, in words


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, bool) or isinstance(b, bool) or isinstance(a, str) or isinstance(b, str):
        return a == b
    return math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-15)


def _find(errors: Mapping[Any, Sequence[float]], value: Any) -> list[float] | None:
    for key, values in errors.items():
        if _same(key, value):
            finite = [v for v in values if math.isfinite(v) and v > 0]
            return finite or None
    return None


def judge(errors: Mapping[Any, Sequence[float]], reference: Mapping[str, Any], quantity: str = "error",
          higher_is_better: bool = False) -> Verdict:
    """`errors[value]`: the finished runs' errors (GNS / constant velocity) at each axis value, or another
    positive `quantity` (with `higher_is_better` where more is better); `reference`: the axis' entry of
    paper_reference.toml (`default`, and `better` or `no_effect`)."""
    sign = -1.0 if higher_is_better else 1.0
    default = _find(errors, reference.get("default"))
    if default is None or len(default) < 2:
        return Verdict(NO_SPREAD, "fewer than two finished seeds at the paper's default")
    band = 2.0 * float(np.std(np.log10(default), ddof=1))

    def mean_log(values: list[float]) -> float:
        return float(np.mean(np.log10(values)))

    if reference.get("no_effect"):
        base = mean_log(default)
        others = [(key, _find(errors, key)) for key in errors if not _same(key, reference["default"])]
        others = [(key, values) for key, values in others if values]
        if not others:
            return Verdict(NOT_RUN, "no value besides the default finished")
        gaps = [(key, mean_log(values) - base) for key, values in others]
        detail = "; ".join(f"{key}: {10 ** gap:.2g}x the default's {quantity}" for key, gap in gaps)
        detail += f" (band: x{10 ** band:.2g} either way)"
        return Verdict(REPRODUCED if all(abs(gap) <= band for _, gap in gaps) else NOT_REPRODUCED, detail)
    pairs = [(a, b, _find(errors, a), _find(errors, b)) for a, b in reference.get("better", [])]
    pairs = [(a, b, ea, eb) for a, b, ea, eb in pairs if ea and eb]
    if not pairs:
        return Verdict(NOT_RUN, "none of the paper's comparisons has both values finished")
    outcomes, words = [], []
    for a, b, ea, eb in pairs:
        log_ratio = mean_log(ea) - mean_log(eb)  # a's quantity over b's
        gap = -sign * log_ratio  # > 0: a is the better one, as the paper found
        outcomes.append("yes" if gap > band else "no" if gap < -band else "tie")
        words.append(f"{a} vs {b}: {10 ** log_ratio:.2g}x ({PAIR_WORDS[outcomes[-1]]})")
    detail = "; ".join(words) + f" ({quantity} of the first over the second; band: x{10 ** band:.2g} either way)"
    if "no" in outcomes:
        return Verdict(NOT_REPRODUCED, detail)
    if all(o == "yes" for o in outcomes):
        return Verdict(REPRODUCED, detail)
    return Verdict(WITHIN_SPREAD, detail)


ERROR = "error"
STEPS_BEFORE_STOP = "rollout steps before a stop"
ONE_STEP = "one-step MSE"


def judge_axis(axis: str, rows: Sequence[RunRow], reference: Mapping[str, Any]) -> dict[str, Verdict]:
    """The verdicts on one ablation axis from its sweep's runs, by quantity: always on the `ERROR` (rollout MSE
    / constant velocity's over the same steps); where a health monitor stopped some rollout, on the mean number
    of rollout steps before the stop (`STEPS_BEFORE_STOP`; with no stop every run covered the whole horizon);
    and where Sec. 5.4 states a direction for the one-step error too (`one_step_better`), on the `ONE_STEP` MSE.
    The one-step error is measured on uncorrupted inputs and needs no rollout, so its seed band tends to be the
    narrowest (GOOP at the cpu tier: x1.2, against x1.6 for the error and x2 for rollout steps)."""
    values = list(dict.fromkeys(r.planned.axes[axis] for r in rows))

    def at_values(measure) -> dict[Any, list[float]]:
        return {v: [measure(r) for r in rows if r.planned.axes[axis] == v] for v in values}

    verdicts = {ERROR: judge(at_values(relative_to_cv), reference)}
    if any_stopped(rows):
        verdicts[STEPS_BEFORE_STOP] = judge(at_values(lambda r: r.metric("rollout_steps")), reference,
                                            STEPS_BEFORE_STOP, higher_is_better=True)
    if reference.get("one_step_better"):
        one_step = {"default": reference.get("default"), "better": reference["one_step_better"]}
        verdicts[ONE_STEP] = judge(at_values(lambda r: r.metric("one_step_mse")), one_step, ONE_STEP)
    return verdicts
