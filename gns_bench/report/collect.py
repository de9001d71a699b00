"""Match a sweep's planned runs (at a tier) with the runs MLflow holds, through `gns_bench.tracking` only.

Every planned run yields a row, found or not: a report shows missing and failed runs instead of
silently dropping them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gns_bench import tracking
from gns_bench.sweep.spec import PlannedRun, SweepSpec, discover_sweeps, load_sweep

METRICS = ("one_step_mse", "rollout_mse", "ot", "mmd", "kinetic_energy_error", "rollout_seconds_per_step")


@dataclass
class RunRow:
    """One planned run and what MLflow knows of it."""

    planned: PlannedRun
    record: tracking.RunRecord | None  # None: MLflow has no run of this name at this tier

    @property
    def status(self) -> str:
        """"finished", "missing", or the MLflow status in lower case (failed, killed, running)."""
        return "missing" if self.record is None else self.record.status.lower()

    @property
    def ok(self) -> bool:
        return self.status == "finished"

    @property
    def run_id(self) -> str:
        return self.record.run_id if self.record else ""

    @property
    def artifact_run_id(self) -> str:
        """Where the run's artifacts (rollouts, stress results) are: the run that trained it, when this run is a
        copy shared from another sweep's (`gns-bench sweep` records those instead of retraining)."""
        return self.tag("shared_from") or self.run_id

    @property
    def split(self) -> str:
        return self.record.params.get("eval.split", "test") if self.record else "test"

    def metric(self, name: str) -> float:
        """`<split>/<name>` (or a train metric by its full name); NaN when absent or the run did not finish."""
        if not self.ok:
            return math.nan
        metrics = self.record.metrics
        return float(metrics.get(f"{self.split}/{name}", metrics.get(name, math.nan)))

    def param(self, name: str, default: str = "") -> str:
        return self.record.params.get(name, default) if self.record else default

    def tag(self, name: str, default: str = "") -> str:
        return self.record.tags.get(name, default) if self.record else default


def resolve_sweep(sweep: str | Path) -> SweepSpec:
    """A sweep file, or a sweep's name (`ablation-noise_std`, `domain-goop`) or file stem under sweeps/."""
    path = Path(sweep)
    if path.suffix == ".toml" and path.is_file():
        return load_sweep(path)
    for candidate in discover_sweeps():
        if candidate.stem == str(sweep) or load_sweep(candidate).name == str(sweep):
            return load_sweep(candidate)
    raise ValueError(f"no sweep named {sweep!r}: pass a sweep file or a name such as 'ablation-noise_std', "
                     "'domain-goop', or 'domains' for the table across domains")


def domain_sweeps() -> list[SweepSpec]:
    """The 16 domain sweeps (sweeps/domains/*.toml), in file order."""
    return [s for s in (load_sweep(p) for p in discover_sweeps()) if s.name.startswith("domain-")]


def collect(sweep: SweepSpec, tier: str) -> list[RunRow]:
    """One row per planned run; the newest FINISHED MLflow run of that name wins, else the newest of any
    status (so a failure shows), else none (missing)."""
    records = tracking.search_sweep_runs(sweep.experiment, tier)
    rows = []
    for planned in sweep.plan(tier):
        named = [r for r in records if r.name == planned.name]  # newest first
        finished = [r for r in named if r.status == "FINISHED"]
        rows.append(RunRow(planned, (finished or named or [None])[0]))
    return rows


def mean_std(values: list[float]) -> tuple[float, float, int]:
    """Mean and standard deviation over the finite values, and how many there were."""
    finite = [v for v in values if v is not None and math.isfinite(v)]
    if not finite:
        return math.nan, math.nan, 0
    return float(np.mean(finite)), float(np.std(finite)), len(finite)


def axis_value_label(value: Any) -> str:
    return str(value).lower() if isinstance(value, bool) else f"{value:g}" if isinstance(value, float) else str(value)
