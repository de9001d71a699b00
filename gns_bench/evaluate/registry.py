"""Metrics of one's own, defined once: register a `Metric` and every evaluation computes it on each rollout, logs
it to MLflow beside the built-in metrics (`<split>/<name>`, the mean over trajectories), keeps it in the run
summaries, and every sweep report shows it as a column of its runs table with its definition under *Metrics*.

    from gns_bench.evaluate.registry import Metric, register_metric

    register_metric(Metric("final_error", lambda r: float(((r.predicted[-1] - r.ground_truth[len(r.predicted) - 1])
                                                            ** 2).sum(-1).mean()),
                           unit="position units²", definition="squared error at the rollout's last step"))

A metric reads one `RolloutResult` (the predicted and true positions of one test trajectory, its initial window
and particle types); where the rollout produced no step it is NaN. The paper's metrics are computed in
`evaluate.py` (Sec. 4.4, App. B.4) and defined in the reports' *Metrics* section.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from gns_bench.evaluate.result import RolloutResult


@dataclass(frozen=True)
class Metric:
    name: str
    compute: Callable[[RolloutResult], float]
    unit: str
    definition: str
    lower_is_better: bool = True


_METRICS: dict[str, Metric] = {}


def register_metric(metric: Metric) -> Metric:
    """Add `metric` to every evaluation and report from now on (a name taken already is refused)."""
    if metric.name in _METRICS and _METRICS[metric.name] is not metric:
        raise ValueError(f"a metric named {metric.name!r} is registered already")
    _METRICS[metric.name] = metric
    return metric


def unregister_metric(name: str) -> None:
    _METRICS.pop(name, None)


def registered() -> list[Metric]:
    return list(_METRICS.values())


def compute_all(result: RolloutResult) -> dict[str, float]:
    """Every registered metric on one rollout (NaN where the rollout has no step)."""
    if result.predicted.shape[0] == 0:
        return {m.name: float("nan") for m in _METRICS.values()}
    return {m.name: float(m.compute(result)) for m in _METRICS.values()}


def definitions() -> list[str]:
    """The registered metrics' lines for a report's *Metrics* section."""
    direction = {True: "lower is better", False: "higher is better"}
    return [f"**{m.name}** ({m.unit}; {direction[m.lower_is_better]}): {m.definition}" for m in _METRICS.values()]
