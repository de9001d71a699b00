"""What a sweep's (or a campaign's) runs would cost here: each run's step rate measured on its own data, and
the training time its steps would take (`gns-bench sweep FILE --tier T --time`).

Tiers define runs by steps (issue #19); this is how those steps are chosen from a measured rate, and how a
campaign is checked against its budget before it starts. Runs that differ only in their seed or in settings
that leave a step's cost unchanged are not told apart: runs with the same model and batch on the same data are
measured once.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from gns_bench.sweep.runner import dataset_run_key, format_plan, prepare, training_data, unstressed_key
from gns_bench.sweep.spec import PlannedRun, SweepSpec
from gns_bench.train.rate import StepRate, measure_step_rate

# Train settings a step's cost does not depend on: runs differing only in these share one measurement.
_COST_FREE = {"seed", "steps", "learning_rate", "learning_rate_final", "learning_rate_decay_steps", "noise_std",
              "position_correction", "checkpoint_every", "log_every", "eval_every", "eval_trajectories",
              "eval_rollout_steps", "max_wall_seconds"}


def cost_key(run: PlannedRun, data_root: Path) -> str:
    """Runs with equal keys cost the same a step: the same data, model and remaining train settings."""
    config = run.config.to_dict()
    config["train"] = {k: v for k, v in config["train"].items() if k not in _COST_FREE}
    config.pop("eval", None)
    config.pop("stress", None)
    return json.dumps({"data": str(training_data(run, data_root)), "config": config}, sort_keys=True, default=str)


def time_runs(runs: list[PlannedRun], status: dict[str, str], data_root: Path, *, steps: int = 20,
              measured: dict[str, StepRate] | None = None, echo: Callable[[str], None] = print
              ) -> dict[str, StepRate]:
    """The step rate of every run whose dataset exists, by run name. `measured`: rates by `cost_key`, shared
    between calls (a campaign's sweeps), filled in here."""
    measured = {} if measured is None else measured
    rates: dict[str, StepRate] = {}
    for run in runs:
        if status.get(run.name) == "dataset missing":
            continue
        key = cost_key(run, data_root)
        if key not in measured:
            echo(f"  timing {run.sweep}/{run.name} on {training_data(run, data_root).name} ...")
            measured[key] = measure_step_rate(run.config, training_data(run, data_root),
                                              steps=min(steps, max(run.config.train.steps - 5, 1)))
        rates[run.name] = measured[key]
    return rates


def _rate(steps_per_second: float) -> str:
    return f"{steps_per_second:.3g}" if steps_per_second < 1000 else f"{steps_per_second:,.0f}"


def format_duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def timing_columns(runs: list[PlannedRun], rates: dict[str, StepRate]) -> dict[str, dict[str, str]]:
    """`format_plan`'s extra columns: each run's steps, measured rate and the training time they make."""
    return {
        "steps": {r.name: f"{r.config.train.steps:,}" for r in runs},
        "steps/s": {name: f"{_rate(rate.steps_per_second)} ({rate.settings})" for name, rate in rates.items()},
        "training time": {r.name: format_duration(rates[r.name].seconds_for(r.config.train.steps))
                          for r in runs if r.name in rates},
    }


def time_to_run(runs: list[PlannedRun], status: dict[str, str], rates: dict[str, StepRate], data_root: Path,
                counted: set[str]) -> tuple[float, int, int]:
    """Training seconds of the runs still to run, (seconds, runs counted, runs whose dataset is missing).
    `counted`: run keys already counted (a campaign's sweeps share points: an ablation's default is the
    domain's run, a stress sweep tests the domain's model), updated here. Stress rollouts are not counted."""
    seconds, runs_counted, missing = 0.0, 0, 0
    for run in runs:
        if status.get(run.name) == "dataset missing":
            missing += 1
            continue
        if status.get(run.name) != "to run":
            continue
        key, model = dataset_run_key(run, data_root), unstressed_key(run, data_root)
        if key in counted or model in counted:  # a stress sweep's model is its domain sweep's run: not trained
            continue
        counted.add(key)
        seconds += rates[run.name].seconds_for(run.config.train.steps)
        runs_counted += 1
    return seconds, runs_counted, missing


def total_line(seconds: float, runs: int, missing: int) -> str:
    line = f"to train: {runs} runs, {format_duration(seconds)} at the rates measured here"
    return line + (f" (and {missing} runs whose dataset is not generated yet, not timed)" if missing else "")


def timed_plan(sweep: SweepSpec, tier: str, data_root: Path, *, steps: int = 20, share: bool = True,
               only: tuple[str, ...] | list[str] = (), measured: dict[str, StepRate] | None = None,
               counted: set[str] | None = None, echo: Callable[[str], None] = print) -> tuple[float, int, int]:
    """Print the sweep's plan with each run's measured rate and training time (generating nothing), then the
    total still to train; returns that total as `time_to_run` does. `measured`, `counted`: shared across a
    campaign's sweeps."""
    runs, status, _ = prepare(sweep, tier, data_root, generate=False, share=share, only=only)
    rates = time_runs(runs, status, data_root, steps=steps, measured=measured, echo=echo)
    echo(format_plan(sweep, tier, runs, status, timing_columns(runs, rates)))
    total = time_to_run(runs, status, rates, data_root, set() if counted is None else counted)
    echo(total_line(*total))
    return total
