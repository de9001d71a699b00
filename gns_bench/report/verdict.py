"""Whether an ablation reproduces the paper's finding on its axis, computed from the run summaries.

Each comparison is an effect with its interval (`report.intervals`): the ratio of geometric means over seeds of
value a's error to value b's, with a 95% t interval on the log errors (Welch's when both arms have two seeds or
more; pooled, the two arms' spread taken as one, when an arm has a single seed, so one seed against three still
gets an interval, wide as it should be). Errors are compared over the same steps for every run (`error_measure`).

- `better = [[a, b], ...]` (Sec. 5.4: the paper found a better than b): *reproduced* when every pair that was
  run has its interval wholly on the paper's side of 1, *contradicted* when some pair has it wholly on the other
  side, else *inconclusive*.
- `no_effect = true` (App. C.1's "little difference"): an equivalence test with the margin `EQUIVALENCE_MARGIN`
  (two one-sided tests at 5%: the 90% interval inside [1/m, m]) against the default, each arm with at least two
  seeds; *reproduced* when every value passes, *contradicted* when some value's 95% interval lies wholly beyond
  the margin, else *inconclusive*. Never drawn from one seed.
- Runs on different CPU kinds are not compared: bf16 arithmetic differs between them, and so did the seeds'
  errors (GOOP's default, cpu tier: 0.436 on an AMD EPYC against 0.283 and 0.303 on an Intel Xeon). A pair
  compares only the runs on the CPU kinds both arms ran on (matched on hardware); none in common: inconclusive.

`higher_is_better` flips the direction for a measure where more is better (rollout steps before a monitor's stop).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats

from gns_bench.evaluate.metrics import DEFAULT_HORIZONS
from gns_bench.report.cells import any_stopped
from gns_bench.report.collect import RunRow
from gns_bench.report.intervals import Interval, ratio_interval
from gns_bench.sweep.cpu_kinds import kind_of

REPRODUCED = "reproduced"
CONTRADICTED = "contradicted"
INCONCLUSIVE = "inconclusive"
NOT_RUN = "inconclusive (the values the paper compares were not run)"
LEVEL = 0.95
EQUIVALENCE_MARGIN = 1.25  # "little difference": within 1.25x either way (App. C.1 gives no number; stated here)


@dataclass(frozen=True)
class Verdict:
    verdict: str
    detail: str  # the comparisons behind it: effects, intervals, seeds, the rule that decided


@dataclass(frozen=True)
class Arm:
    """One axis value's finished runs: their measure and the CPU kind each ran on ("" where unknown)."""

    values: tuple[float, ...]
    kinds: tuple[str, ...]

    @staticmethod
    def of(values: Sequence[float], kinds: Sequence[str] | None = None) -> Arm:
        kinds = tuple(kinds) if kinds is not None else ("",) * len(values)
        kept = [(v, k) for v, k in zip(values, kinds, strict=True) if math.isfinite(v) and v > 0]
        return Arm(tuple(v for v, _ in kept), tuple(k for _, k in kept))

    def on(self, kinds: set[str]) -> tuple[float, ...]:
        return tuple(v for v, k in zip(self.values, self.kinds, strict=True) if k in kinds)


def effect(a: Sequence[float], b: Sequence[float], level: float = LEVEL) -> tuple[Interval, str]:
    """a's geometric mean over b's with its interval, and how the interval was made."""
    if len(a) >= 2 and len(b) >= 2:
        return ratio_interval(a, b, level), "Welch t"
    la, lb = np.log(a), np.log(b)
    estimate = float(np.exp(la.mean() - lb.mean()))
    df = len(a) + len(b) - 2
    squares = float(((la - la.mean()) ** 2).sum() + ((lb - lb.mean()) ** 2).sum())
    if df < 1 or squares == 0.0:
        return Interval(estimate, 0.0, math.inf, level), "one seed a side: no spread to judge by"
    se = math.sqrt(squares / df * (1 / len(a) + 1 / len(b)))
    half = float(stats.t.ppf(0.5 + level / 2, df)) * se
    diff = float(la.mean() - lb.mean())
    return Interval(estimate, math.exp(diff - half), math.exp(diff + half), level), "pooled t"


def interval_text(interval: Interval) -> str:
    """"0.41x [0.2x, 0.84x]", or the estimate alone where there is no interval (one seed a side)."""
    return interval.text(2, "x") if math.isfinite(interval.high) else f"{interval.estimate:.2g}x"


def matched(a: Arm, b: Arm) -> tuple[tuple[float, ...], tuple[float, ...], str]:
    """The two arms' values on the CPU kinds both ran on, and a note when runs were left out."""
    common = set(a.kinds) & set(b.kinds)
    left_out = len(a.values) + len(b.values) - len(a.on(common)) - len(b.on(common))
    note = f", {left_out} run(s) on another CPU kind left out" if left_out and common else ""
    return a.on(common), b.on(common), note


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, bool) or isinstance(b, bool) or isinstance(a, str) or isinstance(b, str):
        return a == b
    return math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-15)


def _find(arms: Mapping[Any, Arm], value: Any) -> Arm | None:
    for key, arm in arms.items():
        if _same(key, value):
            return arm if arm.values else None
    return None


def judge(errors: Mapping[Any, Sequence[float]], reference: Mapping[str, Any], quantity: str = "error",
          higher_is_better: bool = False, kinds: Mapping[Any, Sequence[str]] | None = None) -> Verdict:
    """`errors[value]`: the finished runs' measure at each axis value (positive; lower is better unless
    `higher_is_better`), `kinds[value]` the CPU kind of each (None: all one kind); `reference`: the axis'
    entry of paper_reference.toml (`default`, and `better` or `no_effect`)."""
    arms = {key: Arm.of(values, (kinds or {}).get(key)) for key, values in errors.items()}
    if reference.get("no_effect"):
        return _equivalence(arms, reference["default"], quantity)
    sign = -1.0 if higher_is_better else 1.0
    outcomes, words = [], []
    for a, b in reference.get("better", []):
        arm_a, arm_b = _find(arms, a), _find(arms, b)
        if arm_a is None or arm_b is None:
            continue
        va, vb, note = matched(arm_a, arm_b)
        if not va or not vb:
            outcomes.append("refused")
            words.append(f"{a} vs {b}: not compared (the arms ran on different CPU kinds)")
            continue
        interval, method = effect(va, vb)
        paper_side = interval.high < 1 if sign > 0 else interval.low > 1
        other_side = interval.low > 1 if sign > 0 else interval.high < 1
        outcomes.append("yes" if paper_side else "no" if other_side else "open")
        side = {"yes": "as the paper", "no": "against the paper", "open": "interval spans 1"}[outcomes[-1]]
        words.append(f"{a} vs {b}: {interval_text(interval)} ({side}; {len(va)} vs {len(vb)} seeds, {method}{note})")
    if not outcomes:
        return Verdict(NOT_RUN, "none of the paper's comparisons has both values finished")
    return _decided(outcomes, "no", "yes",
                    "; ".join(words) + f" ({quantity} of the first over the second, 95% interval)")


def _equivalence(arms: Mapping[Any, Arm], default_value: Any, quantity: str) -> Verdict:
    default = _find(arms, default_value)
    others = [(key, arm) for key, arm in arms.items() if not _same(key, default_value) and arm.values]
    if default is None or not others:
        return Verdict(NOT_RUN, "the default or every other value is unfinished")
    m = EQUIVALENCE_MARGIN
    outcomes, words = [], []
    for key, arm in others:
        va, vd, note = matched(arm, default)
        if not va or not vd:
            outcomes.append("refused")
            words.append(f"{key}: not compared (it and the default ran on different CPU kinds)")
            continue
        wide, method = effect(va, vd, LEVEL)
        narrow, _ = effect(va, vd, 1 - 2 * (1 - LEVEL))  # TOST at 5%: the 90% interval
        if len(va) >= 2 and len(vd) >= 2 and 1 / m <= narrow.low and narrow.high <= m:
            outcomes.append("equivalent")
        elif wide.low > m or wide.high < 1 / m:
            outcomes.append("different")
        else:
            outcomes.append("open")
        why = {"equivalent": f"90% interval {narrow.text(2, 'x')} within the margin",
               "different": "beyond the margin",
               "open": ("one seed: equivalence needs two a side" if min(len(va), len(vd)) < 2
                        else "neither within nor beyond the margin")}[outcomes[-1]]
        words.append(f"{key}: {interval_text(wide)} the default's {quantity} ({why}; {len(va)} vs {len(vd)} seeds, "
                     f"{method}{note})")
    return _decided(outcomes, "different", "equivalent", "; ".join(words) + f" (95% interval; margin {m}x either way)")


def _decided(outcomes: list[str], against: str, agrees: str, detail: str) -> Verdict:
    """Contradicted when any comparison went against the finding, reproduced when every one agreed with it (a
    comparison refused or left open makes it inconclusive)."""
    if against in outcomes:
        return Verdict(CONTRADICTED, detail)
    if all(o == agrees for o in outcomes):
        return Verdict(REPRODUCED, detail)
    return Verdict(INCONCLUSIVE, detail)


ERROR = "error"
STEPS_BEFORE_STOP = "rollout steps before a stop"
ONE_STEP = "one-step MSE"
_STOP_STEP = re.compile(r"at step (\d+)")


def first_stop(row: RunRow) -> float:
    """The earliest rollout step at which a monitor stopped one of the run's rollouts (inf: none stopped)."""
    steps = [int(s) for s in _STOP_STEP.findall(row.tag(f"{row.split}/rollouts_stopped"))]
    if steps:
        return float(min(steps))
    return math.inf if not row.metric("rollout_stopped") > 0 else 0.0  # stopped, but the tag lost the step


def error_measure(rows: Sequence[RunRow]) -> tuple[str, str]:
    """The metric a verdict compares over the same steps for every run, and its name in words: the whole-rollout
    MSE when no rollout of `rows` was stopped, else the MSE over the first h steps for the largest logged
    horizon h every rollout of every run reached ("" when none)."""
    done = [r for r in rows if r.ok]
    if not any_stopped(done):
        return "rollout_mse", "whole-rollout MSE"
    reached = min((first_stop(r) for r in done), default=math.inf)
    horizons = [h for h in DEFAULT_HORIZONS if h <= reached and all(math.isfinite(r.metric(f"mse_h{h}")) for r in done)]
    if not horizons:
        return "", ""
    h = max(horizons)
    return f"mse_h{h}", f"MSE over the first {h} rollout steps (every rollout reached step {h})"


def cpu_kind(row: RunRow) -> str:
    """The kind of machine a run trained on, as the runner holds compared runs to one (`sweep/cpu_kinds.py`)."""
    return kind_of(row.record.tags if row.record is not None else {})


def judge_axis(axis: str, rows: Sequence[RunRow], reference: Mapping[str, Any]) -> dict[str, Verdict]:
    """The verdicts on one ablation axis from its sweep's runs, by quantity: always on the `ERROR`, over the same
    steps for every run (`error_measure`); where a health monitor stopped some rollout, on the number of rollout
    steps before the stop (`STEPS_BEFORE_STOP`), which an error over common steps cannot see; and where Sec. 5.4
    states a direction for the one-step error too (`one_step_better`), on the `ONE_STEP` MSE."""
    values = list(dict.fromkeys(r.planned.axes[axis] for r in rows))
    done = [r for r in rows if r.ok]

    def at_values(measure) -> tuple[dict[Any, list[float]], dict[Any, list[str]]]:
        return ({v: [measure(r) for r in done if r.planned.axes[axis] == v] for v in values},
                {v: [cpu_kind(r) for r in done if r.planned.axes[axis] == v] for v in values})

    metric, words = error_measure(rows)
    if metric:
        errors, kinds = at_values(lambda r: r.metric(metric))
        verdicts = {ERROR: judge(errors, reference, words, kinds=kinds)}
    else:
        verdicts = {ERROR: Verdict(INCONCLUSIVE, "no horizon that every rollout reached")}
    if any_stopped(rows):
        steps, kinds = at_values(lambda r: r.metric("rollout_steps"))
        verdicts[STEPS_BEFORE_STOP] = judge(steps, reference, STEPS_BEFORE_STOP, higher_is_better=True, kinds=kinds)
    if reference.get("one_step_better"):
        one_step = {"default": reference.get("default"), "better": reference["one_step_better"]}
        errors, kinds = at_values(lambda r: r.metric("one_step_mse"))
        verdicts[ONE_STEP] = judge(errors, one_step, ONE_STEP, kinds=kinds)
    return verdicts
