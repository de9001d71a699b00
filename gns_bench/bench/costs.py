"""Cost beside error, measured: every baselines-report comparison's models timed one after another on this
machine, on the tier's data. The baselines report (`report/baselines.py`) only reads the result, which its run
summary keeps between regenerations (`MEASURED`)."""

from __future__ import annotations

from collections.abc import Callable
from datetime import date
from pathlib import Path
from typing import Any

from gns_bench import simulators
from gns_bench.report.baselines import architecture_of, baseline_sweeps
from gns_bench.report.collect import domain_sweeps
from gns_bench.report.reference import display_name


def measure_costs(tier: str, data_root: Path, *, steps: int = 40,
                  echo: Callable[[str], None] = print) -> dict[str, Any]:
    """Every comparison's models timed one after another on this machine, on the tier's data (cost
    beside error, like for like). Per comparison domain, the GNS (the domain sweep's first run) and each
    baseline (its sweep's first run: its training noise does not change a step's cost): `steps` steps of the
    run's own training loop, with the precision and compile settings the run would choose here
    (`sweep.timing.time_runs`), and its evaluation's rollout steps (`evaluate.cost`). A run's own training
    time is measured on whatever machine trained it; these are all measured here, in one sitting.
    Comparisons whose data is not generated are left out (`missing`)."""
    from gns_bench.datasets import dataset_complete
    from gns_bench.devices import cpu_identity, resolve_device
    from gns_bench.sweep.runner import evaluation_data, training_data
    from gns_bench.sweep.timing import time_runs
    from gns_bench.tracking import git_sha, hardware_description

    domains = {s.domain: s for s in domain_sweeps()}
    devices: set[str] = set()
    measured: dict[str, object] = {}
    rows: list[dict[str, Any]] = []
    missing: list[str] = []
    for sweep in baseline_sweeps():
        name = display_name(sweep.domain)
        pair = [("GNS", domains[sweep.domain].plan(tier)[0]),
                (simulators.display_name(architecture_of(sweep)), sweep.plan(tier)[0])]
        absent = [path.name for _, run in pair for path in (training_data(run, data_root),
                                                             evaluation_data(run, data_root))
                  if not dataset_complete(path)]
        if absent:
            missing.append(f"{name} ({pair[1][0]}): no dataset {', '.join(sorted(set(absent)))} in the data root")
            continue
        devices.update(str(resolve_device(run.config.train.device)) for _, run in pair)
        costs = time_runs([run for _, run in pair], {}, data_root, steps=steps, measured=measured, echo=echo)
        for model, run in pair:
            if any(r["domain"] == name and r["model"] == model for r in rows):
                continue  # BOXBATH's GNS stands beside two baselines
            cost = costs[run.name]
            rows.append({"domain": name, "model": model, "settings": cost.rate.settings,
                         "train_seconds_per_step": 1.0 / cost.rate.steps_per_second,
                         "rollout_seconds_per_step": cost.evaluation.rollout_seconds
                         / max(cost.evaluation.rollout_steps, 1)})
    hardware = "; ".join(hardware_description(d) for d in sorted(devices or {"cpu"}))
    return {"hardware": hardware, "cpu": cpu_identity(), "date": date.today().isoformat(),
            "git_sha": git_sha(), "tier": tier, "steps": steps, "rows": rows, "missing": missing}
