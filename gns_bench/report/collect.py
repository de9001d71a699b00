"""Match a sweep's planned runs (at a tier) with the runs MLflow holds, and read the rollouts they logged,
through `gns_bench.tracking` only.

Every planned run yields a row, found or not: a report shows missing and failed runs instead of
silently dropping them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gns_bench import tracking
from gns_bench.evaluate.result import RolloutResult
from gns_bench.report.kept import UNFINISHED, read_kept
from gns_bench.sweep.runner import summary_key
from gns_bench.sweep.spec import PlannedRun, SweepSpec, discover_sweeps, load_sweep
from gns_bench.sweep.summaries import read_run_summary, record_from_json, summary_path

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
    def stress_run_id(self) -> str:
        """Where the run's stress results are: its own, when a stress sweep tested another sweep's model
        (tag `stress_tested` = "here", `pipeline.stress_trained`), else where its artifacts are."""
        return self.run_id if self.tag("stress_tested") == "here" else self.artifact_run_id

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
    return [s for s in (load_sweep(p) for p in discover_sweeps()) if s.kind == "domain"]


def stress_sweeps() -> list[SweepSpec]:
    """The stress sweeps (sweeps/stress/*.toml), in file order."""
    return [s for s in (load_sweep(p) for p in discover_sweeps()) if s.kind == "stress"]


def collect(sweep: SweepSpec, tier: str, reports_root: Path | None = None) -> list[RunRow]:
    """One row per planned run: the newest FINISHED MLflow run of that name, else the one the committed run
    summary (`reports_root/<sweep>/<tier>/runs.json`) holds, else the newest MLflow run of any status (so a
    failure, or a run still training, shows), else the unfinished run the report last showed (`report.json`,
    `UNFINISHED`), else none (missing). So a report is rebuilt from its summary when the MLflow store that made
    it is gone, and runs finished since take their place. A run from MLflow that logged curves along training
    (`curve/...`) comes with their history, finished or not."""
    records = tracking.search_sweep_runs(sweep.experiment, tier)
    saved = read_run_summary(summary_path(reports_root, sweep.name, tier)) if reports_root else {}
    shown = read_kept(reports_root / sweep.name / tier).get(UNFINISHED, {}) if reports_root else {}
    rows = []
    for planned in sweep.plan(tier):
        named = [r for r in records if r.name == planned.name]  # newest first
        finished = [r for r in named if r.status == "FINISHED"]
        # an unfinished attempt shows only if it trains what the plan now asks (`_of_this_plan`)
        unfinished = [r for r in named if r.status != "FINISHED" and _of_this_plan(planned, r)]
        kept = record_from_json(shown[planned.name]) if planned.name in shown else None
        record = ((finished or [saved.get(planned.name)] or [None])[0] or (unfinished or [None])[0]
                  or (kept if kept is not None and _of_this_plan(planned, kept) else None))
        if record is not None and record in named and any(k.startswith(tracking.CURVE_PREFIX)
                                                          for k in record.metrics):
            record.curves = {key: tracking.metric_history(record.run_id, key) for key in record.metrics
                             if key.startswith(tracking.CURVE_PREFIX)}
        rows.append(RunRow(planned, record))
    return rows


def _of_this_plan(planned: PlannedRun, record: tracking.RunRecord) -> bool:
    """Whether an unfinished MLflow run of `planned`'s name was training what the plan now asks: its `run_key` is
    the plan's on the datasets it names (a candidate whose recipe changed keeps its name, and an attempt at the
    earlier recipe is another model). A record that names no key or dataset is taken as it is. Finished runs
    are matched by name: a committed summary's may predate a key change that left their model as it was."""
    key = record.tags.get("run_key")
    if not key:
        return True
    expected = summary_key(planned, record)
    return expected is None or expected == key


def unfinished_records(rows: list[RunRow]) -> dict[str, dict]:
    """The unfinished runs a report shows (failed, killed, still training), kept in its `report.json` under
    `UNFINISHED`: the runner's summary holds finished runs only, so a rebuild without MLflow shows them from
    there."""
    return {row.planned.name: dataclasses.asdict(row.record) for row in rows
            if row.record is not None and row.record.status != "FINISHED"}


def mean_std(values: list[float]) -> tuple[float, float, int]:
    """Mean and sample standard deviation (n - 1: two or three seeds are all a spread has here, and the
    population's n would shrink it by 29% or 18%) over the finite values, and how many there were (one
    value: std 0)."""
    finite = [v for v in values if v is not None and math.isfinite(v)]
    if not finite:
        return math.nan, math.nan, 0
    return float(np.mean(finite)), float(np.std(finite, ddof=1)) if len(finite) > 1 else 0.0, len(finite)


def axis_value_label(value: Any) -> str:
    return str(value).lower() if isinstance(value, bool) else f"{value:g}" if isinstance(value, float) else str(value)


def load_rollouts(run_id: str, artifact_path: str, workdir: Path) -> list[RolloutResult]:
    """The rollouts (with their ground truth) a run logged as an npz artifact; none when it has no such file."""
    local = tracking.download_artifacts(run_id, artifact_path, workdir)
    if local is None:
        return []
    with np.load(local) as data:
        keys = sorted({k.split("/")[0] for k in data.files})
        def optional(key: str, name: str):
            return data[f"{key}/{name}"] if f"{key}/{name}" in data.files else None

        results = []
        for k in keys:
            stopped_at, reason = optional(k, "stopped_at"), optional(k, "stop_reason")
            results.append(RolloutResult(data[f"{k}/predicted"], data[f"{k}/ground_truth"],
                                         data[f"{k}/initial_window"], data[f"{k}/particle_type"],
                                         stopped_at=None if stopped_at is None else int(stopped_at),
                                         stop_reason=None if reason is None else str(reason),
                                         birth_step=optional(k, "birth_step")))
        return results
