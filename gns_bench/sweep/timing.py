"""What a sweep's (or a campaign's) runs would cost here: each run's step rate measured on its own data, the
training time its steps would take, and the time its evaluation would take (`evaluate/cost.py`)
(`gns-bench sweep FILE --tier T --time`).

Tiers define runs by steps; this is how those steps are chosen from a measured rate, and how a
campaign is checked against its budget before it starts. Runs that differ only in their seed or in settings
that leave a step's cost unchanged are not told apart: runs with the same model and batch on the same data are
measured once, and their evaluations once per evaluation config and evaluation data.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from gns_bench.data.format import load_split, read_metadata
from gns_bench.durations import format_duration
from gns_bench.evaluate.cost import EvaluationCost, evaluation_cost
from gns_bench.sweep.runner import dataset_run_key, evaluation_data, format_plan, prepare, training_data, unstressed_key
from gns_bench.sweep.spec import PlannedRun, SweepSpec
from gns_bench.train.checkpoints import build_simulator
from gns_bench.train.rate import StepRate, measure_step_rate

# Train settings a step's cost does not depend on: runs differing only in these share one measurement.
_COST_FREE = {"seed", "steps", "learning_rate", "learning_rate_final", "learning_rate_decay_steps", "noise_std",
              "position_correction", "checkpoint_every", "log_every", "eval_every", "eval_trajectories",
              "eval_rollout_steps", "max_wall_seconds"}


@dataclass(frozen=True)
class RunCost:
    """A planned run's measured cost here: its training step rate and its evaluation's time."""

    rate: StepRate
    evaluation: EvaluationCost

    def training_seconds(self, run: PlannedRun) -> float:
        return self.rate.seconds_for(run.config.train.steps)


def cost_key(run: PlannedRun, data_root: Path) -> str:
    """Runs with equal keys cost the same a step: the same data, model and remaining train settings."""
    config = run.config.to_dict()
    config["train"] = {k: v for k, v in config["train"].items() if k not in _COST_FREE}
    config.pop("eval", None)
    config.pop("stress", None)
    return json.dumps({"data": str(training_data(run, data_root)), "config": config}, sort_keys=True, default=str)


def evaluation_key(run: PlannedRun, data_root: Path) -> str:
    """Runs with equal keys cost the same to evaluate: the same model, evaluation config and evaluation data."""
    model = json.loads(cost_key(run, data_root))["config"]
    return json.dumps({"data": str(evaluation_data(run, data_root)), "model": model,
                       "eval": run.config.to_dict()["eval"]}, sort_keys=True, default=str)


def measure_evaluation(run: PlannedRun, data_root: Path) -> EvaluationCost:
    """`evaluation_cost` of the run's (untrained) model on its evaluation data."""
    data = evaluation_data(run, data_root)
    metadata = read_metadata(data)
    simulator = build_simulator(run.config, metadata)
    trajectories = load_split(data, run.config.eval.split, metadata,
                              min_length=simulator.input_sequence_length + 1)
    return evaluation_cost(simulator, trajectories, run.config.eval)


def time_runs(runs: list[PlannedRun], status: dict[str, str], data_root: Path, *, steps: int = 40,
              measured: dict[str, object] | None = None, echo: Callable[[str], None] = print
              ) -> dict[str, RunCost]:
    """The cost of every run whose dataset exists, by run name. `measured`: step rates by `cost_key` and
    evaluation costs by `evaluation_key`, shared between calls (a campaign's sweeps), filled in here."""
    measured = {} if measured is None else measured
    costs: dict[str, RunCost] = {}
    for run in runs:
        if status.get(run.name) == "dataset missing":
            continue
        key, eval_key = cost_key(run, data_root), "eval:" + evaluation_key(run, data_root)
        if key not in measured:
            echo(f"  timing {run.sweep}/{run.name} on {training_data(run, data_root).name} ...")
            measured[key] = measure_step_rate(run.config, training_data(run, data_root),
                                              steps=min(steps, max(run.config.train.steps - 5, 1)))
        if eval_key not in measured:
            echo(f"  timing {run.sweep}/{run.name}'s evaluation on {evaluation_data(run, data_root).name} ...")
            measured[eval_key] = measure_evaluation(run, data_root)
        costs[run.name] = RunCost(measured[key], measured[eval_key])
    return costs


def _rate(steps_per_second: float) -> str:
    return f"{steps_per_second:.3g}" if steps_per_second < 1000 else f"{steps_per_second:,.0f}"


def timing_columns(runs: list[PlannedRun], costs: dict[str, RunCost]) -> dict[str, dict[str, str]]:
    """`format_plan`'s extra columns: each run's steps, measured rate, the training time they make, and the
    time its evaluation would take (rollouts, one-step windows, distributional metrics)."""
    timed = [r for r in runs if r.name in costs]
    return {
        "steps": {r.name: f"{r.config.train.steps:,}" for r in runs},
        "steps/s": {r.name: f"{_rate(costs[r.name].rate.steps_per_second)} ({costs[r.name].rate.settings})"
                    for r in timed},
        "training time": {r.name: format_duration(costs[r.name].training_seconds(r)) for r in timed},
        "evaluation time": {r.name: f"{format_duration(costs[r.name].evaluation.seconds)} "
                                    f"({costs[r.name].evaluation.rollout_steps:,} rollout steps)" for r in timed},
    }


@dataclass
class Total:
    """What is still to run: training and evaluation seconds, runs counted, runs whose dataset is missing."""

    training_seconds: float = 0.0
    evaluation_seconds: float = 0.0
    runs: int = 0
    missing: int = 0

    def add(self, other: Total) -> None:
        self.training_seconds += other.training_seconds
        self.evaluation_seconds += other.evaluation_seconds
        self.runs += other.runs
        self.missing += other.missing


def time_to_run(runs: list[PlannedRun], status: dict[str, str], costs: dict[str, RunCost], data_root: Path,
                counted: set[str]) -> Total:
    """The training and evaluation time of the runs still to run. `counted`: run keys already counted (a
    campaign's sweeps share points: an ablation's default is the domain's run, a stress sweep tests the
    domain's model), updated here. Stress rollouts are not counted."""
    total = Total()
    for run in runs:
        if status.get(run.name) == "dataset missing":
            total.missing += 1
            continue
        if status.get(run.name) != "to run":
            continue
        key, model = dataset_run_key(run, data_root), unstressed_key(run, data_root)
        if key in counted or model in counted:  # a stress sweep's model is its domain sweep's run: not trained
            continue
        counted.add(key)
        total.training_seconds += costs[run.name].training_seconds(run)
        total.evaluation_seconds += costs[run.name].evaluation.seconds
        total.runs += 1
    return total


def total_line(total: Total) -> str:
    line = (f"to run: {total.runs} runs, {format_duration(total.training_seconds)} of training and "
            f"{format_duration(total.evaluation_seconds)} of evaluation at the rates measured here")
    if total.missing:
        line += f" (and {total.missing} runs whose dataset is not generated yet, not timed)"
    return line


def timed_plan(sweep: SweepSpec, tier: str, data_root: Path, *, steps: int = 40, share: bool = True,
               only: tuple[str, ...] | list[str] = (), measured: dict[str, object] | None = None,
               counted: set[str] | None = None, echo: Callable[[str], None] = print,
               reports_root: Path | None = None) -> Total:
    """Print the sweep's plan with each run's measured rate, training and evaluation time (generating nothing),
    then the total still to run; returns that total. `measured`, `counted`: shared across a campaign's
    sweeps. `reports_root`: where the committed run summaries are (`runner.prepare`)."""
    runs, status, _ = prepare(sweep, tier, data_root, generate=False, share=share, only=only,
                              reports_root=reports_root)
    costs = time_runs(runs, status, data_root, steps=steps, measured=measured, echo=echo)
    echo(format_plan(sweep, tier, runs, status, timing_columns(runs, costs)))
    total = time_to_run(runs, status, costs, data_root, set() if counted is None else counted)
    echo(total_line(total))
    return total
