"""Train and evaluate as tracked MLflow runs: the library API the CLI and the sweep runner call."""

from __future__ import annotations

import csv
import json
import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from gns_bench import simulators, tracking
from gns_bench.config import (
    STRESS_TESTS,
    Config,
    ConfigError,
    EvalConfig,
    StressConfig,
    apply_overrides,
    config_from_dict,
    resolve_for_dataset,
    saved_config,
)
from gns_bench.data.format import DatasetError, load_split, read_metadata
from gns_bench.data.integrity import check_before_run
from gns_bench.devices import resolve_device
from gns_bench.evaluate.evaluate import Evaluation, evaluate, rollout_errors, save_rollouts
from gns_bench.evaluate.monitors import MonitorTripped
from gns_bench.evaluate.plots import plot_rollout
from gns_bench.evaluate.rollout import rollout
from gns_bench.model.simulator import LearnedSimulator
from gns_bench.train import distributed
from gns_bench.train.checkpoints import CHECKPOINT_NAME, load_simulator
from gns_bench.train.loop import check_resumable, load_training_split, train

DEFAULT_EXPERIMENT = "gns-bench"
RUN_ID_FILE = "mlflow_run_id"


@dataclass
class RunSummary:
    run_id: str
    out_dir: Path
    checkpoint: Path | None
    metrics: dict[str, float]


def _dataset_tags(dataset_dir: str | Path) -> dict[str, Any]:
    meta = read_metadata(dataset_dir)
    return {"dataset": meta.name or Path(dataset_dir).name, "dataset_path": str(Path(dataset_dir).resolve()),
            "dataset_hash": meta.content_hash or "unknown",
            "dataset_tier": (meta.generator or {}).get("tier", "")}


def write_evaluation_artifacts(evaluation: Evaluation, out_dir: Path, bounds: list[list[float]],
                               prefix: str, model: str = "GNS") -> list[Path]:
    """Rollouts (npz), per-trajectory metrics (csv) and pictures of the best and worst rollouts (`model`: the
    architecture's name, `simulators.display_name`, on the pictures)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [save_rollouts(evaluation, out_dir / f"{prefix}_rollouts.npz")]
    tripped = {f"{i:05d}": r.stopped_by for i, r in enumerate(evaluation.rollouts)
               if isinstance(r.stopped_by, MonitorTripped)}
    (out_dir / f"{prefix}_monitor_states.npz").unlink(missing_ok=True)  # an earlier evaluation's
    if tripped:  # the state each monitor stopped on, with what it saw
        np.savez_compressed(out_dir / f"{prefix}_monitor_states.npz",
                            **{f"{key}/position": stop.position for key, stop in tripped.items()},
                            **{f"{key}/step": np.array(stop.step) for key, stop in tripped.items()},
                            **{f"{key}/monitor": np.array(stop.monitor) for key, stop in tripped.items()})
        paths.append(out_dir / f"{prefix}_monitor_states.npz")
    table = out_dir / f"{prefix}_per_trajectory.csv"
    with table.open("w", newline="") as f:
        # every key any trajectory has: a rollout stopped before step 100 has no `mse_h100`, a later one does
        fields = list(dict.fromkeys(key for row in evaluation.per_trajectory for key in row))
        writer = csv.DictWriter(f, fieldnames=fields, restval="")
        writer.writeheader()
        writer.writerows(evaluation.per_trajectory)
    paths.append(table)
    if not evaluation.rollouts:  # `eval.metrics` without "rollout": nothing to draw
        return paths
    ranked = sorted(range(len(evaluation.per_trajectory)),
                    key=lambda i: evaluation.per_trajectory[i]["rollout_mse"])
    for label, index in (("best", ranked[0]), ("worst", ranked[-1])):
        if evaluation.rollouts[index].predicted.shape[0]:
            mse = evaluation.per_trajectory[index]["rollout_mse"]
            paths.append(plot_rollout(evaluation.rollouts[index], out_dir / f"{prefix}_rollout_{label}.png",
                                      bounds, title=f"{label} trajectory {index}: rollout MSE {mse:.3g}",
                                      name=model))
    return paths


# Tags an evaluation may set; a re-evaluation removes the ones it does not set again
EVALUATION_TAGS = ("rollouts_stopped", "rollouts_flagged", "ot_method", "rollout_compile", "neighbour_skin")


def _log_evaluation(run: tracking.Run, evaluation: Evaluation, out_dir: Path, bounds: list[list[float]],
                    split: str, model: str = "GNS") -> None:
    run.delete_tags([f"{split}/{key}" for key in EVALUATION_TAGS if key not in evaluation.tags])
    run.log_metrics({f"{split}/{key}": value for key, value in evaluation.metrics.items()})
    run.set_tags({f"{split}/{key}": value for key, value in evaluation.tags.items()})
    for path in write_evaluation_artifacts(evaluation, out_dir, bounds, split, model):
        run.log_artifact(path, "evaluation")


OWNER_FILE = "owner.pid"  # the process training in a run directory, while it does


@contextmanager
def owned(out_dir: Path) -> Iterator[None]:
    """Mark `out_dir` as this process's while the block runs (`end_if_abandoned` reads it)."""
    owner = out_dir / OWNER_FILE
    owner.write_text(f"{os.getpid()}\n")
    try:
        yield
    finally:
        owner.unlink(missing_ok=True)


def end_if_abandoned(out_dir: Path) -> bool:
    """A run directory whose MLflow run is still RUNNING with no live process behind it (killed with SIGKILL, a
    lost machine): end that run KILLED, so the store shows no run as live that nothing will finish. True when
    it did."""
    id_file = out_dir / RUN_ID_FILE
    if not id_file.exists():
        return False
    owner = out_dir / OWNER_FILE
    if owner.exists():
        try:
            os.kill(int(owner.read_text().strip()), 0)
            return False  # its process is alive (perhaps still training)
        except (ValueError, ProcessLookupError):
            pass
        except PermissionError:  # alive, another user's
            return False
    reason = f"its process ended without finishing it (found by the next command on {out_dir})"
    return tracking.end_abandoned_run(id_file.read_text().strip(), reason)


def train_run(config: Config, dataset_dir: str | Path, out_dir: str | Path, *,
              experiment: str = DEFAULT_EXPERIMENT, run_name: str | None = None, resume: bool = False,
              evaluate_after: bool = True, progress: bool = True,
              extra_params: dict[str, Any] | None = None, extra_tags: dict[str, Any] | None = None,
              eval_dataset_dir: str | Path | None = None) -> RunSummary:
    """Train (resuming the same MLflow run when `resume`), then evaluate on `config.eval.split`, of
    `eval_dataset_dir` when given (another dataset of the domain: a study's common test set), else of the
    training data; `train.eval_every`'s curve uses that dataset's validation split.

    The config is resolved against the dataset first, so the run logs plain numbers (`resolve_for_dataset`).
    Under torchrun only rank 0 tracks and evaluates; the other ranks just train.
    """
    # Everything that can refuse the input happens before a run folder or an MLflow run exists: the data and
    # their content hash, every split the run will read (and any other there), the checkpoint of a resume.
    try:  # an unknown simulator is refused before anything is created
        simulators.get(config.model.architecture)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    meta = read_metadata(dataset_dir)
    config = resolve_for_dataset(config, meta.default_connectivity_radius)
    min_length = config.model.input_sequence_length + 1
    evaluated_on = eval_dataset_dir or dataset_dir
    needed_there = (((config.eval.split,) if evaluate_after else ()) + (("valid",) if config.train.eval_every else ()))
    if eval_dataset_dir is None:
        check_before_run(dataset_dir, meta, needed=("train", *needed_there), min_length=min_length)
    else:
        check_before_run(dataset_dir, meta, needed=("train",), min_length=min_length)
        check_before_run(evaluated_on, read_metadata(evaluated_on), needed=needed_there, min_length=min_length)
    trajectories = load_training_split(config, dataset_dir, meta)
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise NotADirectoryError(f"{out_dir} is a file; the run's output (--out) is a directory")
    if resume and (out_dir / CHECKPOINT_NAME).exists():  # a checkpoint that cannot resume fails before MLflow
        check_resumable(out_dir / CHECKPOINT_NAME, config, meta)
    elif config.train.init_from:  # a branch: its checkpoint must exist and fit, before anything is created
        check_resumable(Path(config.train.init_from), config, meta, branch=True)
    if distributed.launched_rank() != 0:
        train(config, dataset_dir, out_dir, resume=resume, progress=False, trajectories=trajectories)
        return RunSummary("", out_dir, None, {})
    if not resume and (out_dir / CHECKPOINT_NAME).exists():
        raise FileExistsError(f"{out_dir / CHECKPOINT_NAME} exists; pass resume=True (--resume) or choose "
                              "another out dir")
    out_dir.mkdir(parents=True, exist_ok=True)
    device = str(resolve_device(config.train.device))
    previous = out_dir / RUN_ID_FILE
    end_if_abandoned(out_dir)
    run_id = previous.read_text().strip() if resume and previous.exists() else None
    params = {**config.flat(), "dataset_dir": str(dataset_dir), **(extra_params or {})}
    tags = {**tracking.environment_tags(device), **_dataset_tags(dataset_dir), "kind": "train",
            **(extra_tags or {})}
    tracked = (tracking.continue_run(run_id, tags=tags) if run_id
               else tracking.start_run(experiment, run_name or out_dir.name, params=params, tags=tags))
    with tracked as run, owned(out_dir):
        previous.write_text(run.run_id + "\n")
        run.log_dict(config.to_dict(), "config.json")
        if eval_dataset_dir is not None:
            run.set_tags({f"eval_{key}": value for key, value in _dataset_tags(eval_dataset_dir).items()})
        on_eval = _curve_logger(run, config, evaluated_on, device) if config.train.eval_every else None
        result = train(config, dataset_dir, out_dir, resume=resume, progress=progress, trajectories=trajectories,
                       on_log=lambda step, metrics: run.log_metrics(metrics, step=step), on_eval=on_eval)
        trained = {"train/steps_per_second": result.steps_per_second} if result.final_step > result.start_step else {}
        run.log_metrics({**trained,  # a resume with no step left (its evaluation was cut) keeps the last call's rate
                         "train/final_step": result.final_step, "train/wall_time_s": result.wall_time_s,
                         "train/curve_eval_seconds": result.eval_seconds})
        if result.oversubscribed:  # another job competed for the cores: these timings are not comparable
            run.set_tags({"train/oversubscribed": result.oversubscribed})
        if result.allocator:
            run.set_tags({"train/allocator": result.allocator})
        if result.speed is not None:  # what "auto" chose, or the config's own settings
            run.set_tags({"train/precision_used": result.speed.precision,
                          "train/compile_used": str(result.speed.compile),
                          "train/speed_settings": result.speed.describe()})
            if result.speed.threads is not None:  # the thread count was chosen after the run's tags were set
                run.set_tags({"hardware": tracking.hardware_description(device)})
        run.log_artifact(result.checkpoint, "checkpoint")
        metrics: dict[str, float] = {}
        if evaluate_after:
            simulator, _, _ = load_simulator(result.checkpoint, device)
            metrics = _evaluate_into(run, simulator, evaluated_on, config.eval, out_dir, device, progress).metrics
            if config.stress.enabled:
                metrics = {**metrics, **_stress_and_log(run, simulator, config, dataset_dir, out_dir, device,
                                                        progress)}
        return RunSummary(run.run_id, out_dir, result.checkpoint, metrics)


# What the error-against-training-time curve logs (`curve/<name>` at the training step, beside
# `curve/train_seconds`): the paper's MSEs, the like-for-like baseline, and rollouts a monitor stopped.
CURVE_METRICS = ("rollout_mse", "rollout_mse_moving", "baseline_cv_same_steps_mse", "one_step_mse", "mse_h1",
                 "mse_h10", "mse_h20", "mse_h100", "rollout_steps", "rollout_stopped", "gravity_ratio",
                 "held_gravity_ratio", "held_fall_ratio", "rollout_gravity_ratio", "landing_ratio",
                 "wall_pass_fraction", "wall_depth", "com_fall_ratio", "steps_before_trip",
                 "rollout_mse_held", "baseline_cv_rollout_mse", "mse_h1_held", "mse_h10_held", "mse_h20_held",
                 "mse_h100_held")


def _curve_logger(run: tracking.Run, config: Config, dataset_dir: str | Path, device: str
                  ) -> Callable[[LearnedSimulator, int, float], None]:
    """`train`'s `on_eval`: the model on the first `train.eval_trajectories` validation trajectories, rolled
    out `train.eval_rollout_steps` steps (no distributional metrics), logged into `run` at the step."""
    tc = config.train
    meta = read_metadata(dataset_dir)
    valid = load_split(dataset_dir, "valid", meta, min_length=config.model.input_sequence_length + 1)
    eval_config = replace(config.eval, split="valid", max_trajectories=tc.eval_trajectories,
                          rollout_steps=tc.eval_rollout_steps, distribution_steps=0,
                          one_step_windows=min(config.eval.one_step_windows or 20, 20))

    def log_curve_point(simulator: LearnedSimulator, step: int, train_seconds: float) -> None:
        evaluation = evaluate(simulator, valid, eval_config, device=device, progress=False, gravity=meta.gravity,
                              walls=meta.walls)
        run.log_metrics({tracking.CURVE_PREFIX + key: evaluation.metrics[key] for key in CURVE_METRICS
                         if key in evaluation.metrics} | {tracking.CURVE_PREFIX + "train_seconds": train_seconds},
                        step=step)

    return log_curve_point


def _evaluate_into(run: tracking.Run, simulator: LearnedSimulator, dataset_dir: str | Path, eval_config: EvalConfig,
                   out_dir: Path, device: str, progress: bool, scene_bounds: bool = False) -> Evaluation:
    """Evaluate `simulator` on `eval_config.split` of a dataset and log it all into `run`: metrics
    `<split>/...`, tags, and the artifacts `write_evaluation_artifacts` makes in `out_dir`.
    `scene_bounds`: roll out inside the dataset's own walls (a larger arena than the training data's)."""
    meta = read_metadata(dataset_dir)
    if meta.dim != simulator.dim:
        raise ValueError(f"{dataset_dir}: dim {meta.dim} does not match the simulator's dim {simulator.dim}")
    trajectories = load_split(dataset_dir, eval_config.split, meta,
                              min_length=simulator.input_sequence_length + 1)
    started = time.perf_counter()
    evaluation = evaluate(simulator, trajectories, eval_config, device=device, progress=progress,
                          bounds=meta.bounds if scene_bounds else None, gravity=meta.gravity, walls=meta.walls)
    # what the evaluation cost (the front page sums it over a campaign; `sweep/timing.py` estimates it before)
    evaluation.metrics["evaluation_seconds"] = time.perf_counter() - started
    _log_evaluation(run, evaluation, out_dir, meta.bounds, eval_config.split,
                    simulators.display_name(simulator.architecture))
    return evaluation


def _stress_and_log(run: tracking.Run, simulator: Any, config: Config, dataset_dir: str | Path, out_dir: Path,
                    device: str, progress: bool) -> dict[str, float]:
    """Run `config.stress` and log it into `run`: metrics `stress/<test>/...` and
    `generalisation/<variant>/...`, each test's curves (JSON) and figure, monitors that tripped as tags."""
    from gns_bench.evaluate.stress_plots import plot_stress
    from gns_bench.stress.run import run_stress

    outcome = run_stress(simulator, config, dataset_dir, device=device, progress=progress)
    stress_dir = out_dir / "stress"
    stress_dir.mkdir(parents=True, exist_ok=True)
    logged: dict[str, float] = {}
    training_length = read_metadata(dataset_dir).sequence_length
    for result in outcome.results:
        values = {f"stress/{result.name}/{key}": value for key, value in result.metrics.items()}
        run.log_metrics(values)
        logged.update(values)
        record = {"name": result.name, "metrics": result.metrics, "curves": result.curves, "trips": result.trips,
                  "notes": result.notes}
        path = stress_dir / f"{result.name}.json"
        path.write_text(json.dumps(record, allow_nan=True) + "\n")
        run.log_artifact(path, "stress")
        figure = plot_stress(result, stress_dir / f"{result.name}.png",
                             training_length=training_length if result.name == "horizon" else None)
        run.log_artifact(figure, "stress")
        if result.trips:
            run.set_tags({f"stress/{result.name}/trips": "; ".join(result.trips)[:5000]})
    for variant, (evaluation, scene_meta) in outcome.generalisation.items():
        values = {f"generalisation/{variant}/{key}": value for key, value in evaluation.metrics.items()}
        run.log_metrics(values)
        logged.update(values)
        run.set_tags({f"generalisation/{variant}/{key}": value for key, value in evaluation.tags.items()})
        for path in write_evaluation_artifacts(evaluation, stress_dir / variant, scene_meta.bounds, variant,
                                               simulators.display_name(simulator.architecture)):
            run.log_artifact(path, f"generalisation/{variant}")
    run.set_tags({"stress/tests": ",".join(r.name for r in outcome.results),
                  "generalisation/datasets": ",".join(outcome.generalisation)})
    if outcome.skipped:
        run.set_tags({"stress/skipped": "; ".join(outcome.skipped)[:5000]})
    return logged


def stress_run(checkpoint: str | Path, dataset_dir: str | Path, stress_overrides: list[str] | None = None, *,
               out_dir: str | Path | None = None, experiment: str = DEFAULT_EXPERIMENT, device: str = "auto",
               progress: bool = True) -> RunSummary:
    """Stress-test a checkpoint trained on `dataset_dir` as its own MLflow run (kind "stress").

    `stress_overrides` are `stress.key=value` strings over the checkpoint's config; when they name neither
    `stress.tests` nor `stress.generalisation`, every stress test runs."""
    torch_device = str(resolve_device(device))
    simulator, config, _ = load_simulator(checkpoint, torch_device)
    changes = apply_overrides({}, stress_overrides or [])
    if set(changes) - {"stress"}:
        raise ConfigError(f"stress takes only stress.* overrides, got sections {sorted(set(changes) - {'stress'})}")
    stress = changes.get("stress", {})
    if "tests" not in stress and "generalisation" not in stress:
        stress["tests"] = list(STRESS_TESTS)
    config = config_from_dict({**config.to_dict(), "stress": {**config.to_dict()["stress"], **stress}},
                              f"{checkpoint} + overrides")
    checkpoint = Path(checkpoint)
    out_dir = Path(out_dir) if out_dir else _next_to(checkpoint)
    params = {**config.flat(), "checkpoint": str(checkpoint), "dataset_dir": str(dataset_dir)}
    tags = {**tracking.environment_tags(torch_device), **_dataset_tags(dataset_dir), "kind": "stress"}
    with tracking.start_run(experiment, f"stress-{Path(dataset_dir).name}", params=params, tags=tags) as run:
        metrics = _stress_and_log(run, simulator, config, dataset_dir, out_dir, torch_device, progress)
        return RunSummary(run.run_id, out_dir, None, metrics)


def stress_trained(source: tracking.RunRecord, stress: StressConfig, dataset_dir: str | Path, out_dir: str | Path,
                   *, experiment: str, run_name: str, extra_params: dict[str, Any] | None = None,
                   extra_tags: dict[str, Any] | None = None, device: str = "auto", progress: bool = True
                   ) -> RunSummary:
    """The stress tests `stress` of the model that MLflow run `source` trained on `dataset_dir`, as a new run:
    `source`'s params, metrics and tags (tag `shared_from` = its run id, where its rollouts stay) with the
    stress results logged as a trained run's are. Its checkpoint comes from `out_dir` when an earlier attempt
    fetched it, else from `source`'s artifacts. The run ends FINISHED only once every test is logged."""
    out_dir = Path(out_dir)
    checkpoint = out_dir / CHECKPOINT_NAME
    if not checkpoint.exists():
        fetched = tracking.download_artifacts(source.run_id, f"checkpoint/{CHECKPOINT_NAME}", out_dir / "fetch")
        if fetched is None:
            raise FileNotFoundError(f"run {source.run_id} ({source.name}) logged no checkpoint to stress-test")
        fetched.replace(checkpoint)
    torch_device = str(resolve_device(device))
    simulator, config, _ = load_simulator(checkpoint, torch_device)
    config = config_from_dict({**config.to_dict(), "stress": asdict(stress)}, f"{checkpoint} + [stress]")
    params = {**source.params, **tracking.as_param_strings(config.flat()), **(extra_params or {})}
    tags = {**{k: v for k, v in source.tags.items() if not k.startswith("mlflow.")}, **(extra_tags or {}),
            "shared_from": source.run_id, "stress_tested": "here"}  # report/collect.py `stress_run_id`
    with tracking.start_run(experiment, run_name, params=params, tags=tags) as run:
        run.log_metrics(source.metrics)
        metrics = _stress_and_log(run, simulator, config, dataset_dir, out_dir, torch_device, progress)
        return RunSummary(run.run_id, out_dir, checkpoint, {**source.metrics, **metrics})


@dataclass
class SavedRollout:
    npz: Path  # predicted, ground_truth, initial_window, particle_type
    png: Path
    steps: int
    errors: dict[str, float]  # `evaluate.rollout_errors`: the paper's rollout MSE and the others


def save_rollout(checkpoint: str | Path, dataset_dir: str | Path, split: str = "test", index: int = 0,
                 steps: int | None = None, out_stem: str | Path | None = None, device: str = "auto") -> SavedRollout:
    """Roll a checkpoint out on one trajectory of a split; save it with its ground truth (npz) and a picture,
    `<out_stem>.npz` and `.png` (default stem `rollout-<split>-<index>`)."""
    torch_device = resolve_device(device)
    simulator, config, _ = load_simulator(checkpoint, torch_device)
    meta = read_metadata(dataset_dir)
    trajectories = load_split(dataset_dir, split, meta, min_length=config.model.input_sequence_length + 1)
    if not 0 <= index < len(trajectories):
        raise DatasetError(Path(dataset_dir) / f"{split}.h5", f"no trajectory {index} (the split has "
                           f"{len(trajectories)})")
    result = rollout(simulator, trajectories[index], steps, device=torch_device)
    stem = Path(out_stem) if out_stem else Path(f"rollout-{split}-{index}")
    npz = stem.with_name(stem.name + ".npz")
    np.savez_compressed(npz, predicted=result.predicted, ground_truth=result.ground_truth,
                        initial_window=result.initial_window, particle_type=result.particle_type)
    errors = rollout_errors(result, trajectories[index].num_steps)
    png = plot_rollout(result, stem.with_name(stem.name + ".png"), meta.bounds,
                       title=f"rollout MSE {errors['rollout_mse']:.3g}",
                       name=simulators.display_name(simulator.architecture))
    return SavedRollout(npz, Path(png), result.predicted.shape[0], errors)


def _next_to(checkpoint: Path) -> Path:
    """The run directory of a checkpoint given as a file or as its directory."""
    return checkpoint if checkpoint.is_dir() else checkpoint.parent


def evaluate_run(checkpoint: str | Path, dataset_dir: str | Path, eval_config: EvalConfig | None = None, *,
                 out_dir: str | Path | None = None, experiment: str = DEFAULT_EXPERIMENT,
                 device: str = "auto", progress: bool = True) -> RunSummary:
    """Evaluate a checkpoint on a dataset split as its own MLflow run (rollouts inside that dataset's walls)."""
    torch_device = str(resolve_device(device))
    simulator, config, _ = load_simulator(checkpoint, torch_device)
    config = replace(config, eval=eval_config or config.eval)
    check_before_run(dataset_dir, read_metadata(dataset_dir), needed=(config.eval.split,),
                     min_length=simulator.input_sequence_length + 1)  # before an MLflow run exists
    checkpoint = Path(checkpoint)
    out_dir = Path(out_dir) if out_dir else _next_to(checkpoint) / "evaluation"
    params = {**config.flat(), "checkpoint": str(checkpoint), "dataset_dir": str(dataset_dir)}
    tags = {**tracking.environment_tags(torch_device), **_dataset_tags(dataset_dir), "kind": "evaluate"}
    with tracking.start_run(experiment, f"evaluate-{config.eval.split}", params=params, tags=tags) as run:
        evaluation = _evaluate_into(run, simulator, dataset_dir, config.eval, out_dir, torch_device, progress,
                                    scene_bounds=True)
        return RunSummary(run.run_id, out_dir, None, evaluation.metrics)


def trained_eval_config(out_dir: str | Path, **changes: Any) -> EvalConfig:
    """The evaluation settings a run directory's training was given (its `config.json`), with `changes`."""
    path = Path(out_dir) / "config.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not a run directory (training writes config.json there)")
    eval_config = replace(saved_config(json.loads(path.read_text()), str(path)).eval, **changes)
    eval_config.validate()
    return eval_config


def reevaluate_run(run_id: str, dataset_dir: str | Path, out_dir: str | Path, eval_config: EvalConfig, *,
                   reason: str, device: str = "auto", progress: bool = True) -> RunSummary:
    """Evaluate a trained run's final checkpoint (`out_dir/checkpoint.pt`) again, into that same MLflow run,
    when the evaluation changed after it finished. Its metrics take the new values (MLflow keeps the old
    ones in each metric's history), evaluation tags it no longer earns are removed, its artifacts are
    replaced, and tag `reevaluated` says when and why. A re-evaluation that fails leaves the run FAILED, so
    the sweep resumes it (from the final checkpoint: evaluation only) rather than trusting half its metrics."""
    out_dir = Path(out_dir)
    checkpoint = out_dir / "checkpoint.pt"
    if not checkpoint.exists():
        raise FileNotFoundError(f"{checkpoint}: run {run_id} has no checkpoint here to evaluate again")
    owner = (out_dir / RUN_ID_FILE).read_text().strip() if (out_dir / RUN_ID_FILE).exists() else run_id
    if owner != run_id:
        raise ValueError(f"{out_dir / RUN_ID_FILE}: this checkpoint belongs to MLflow run {owner}, not {run_id}")
    torch_device = str(resolve_device(device))
    simulator, _, _ = load_simulator(checkpoint, torch_device)
    split = eval_config.split
    with tracking.continue_run(run_id) as run:
        run.log_params({k: v for k, v in Config(eval=eval_config).flat().items()
                        if k.startswith("eval.") and k not in run.params})  # fields added since it was logged
        evaluation = _evaluate_into(run, simulator, dataset_dir, eval_config, out_dir, torch_device, progress)
        if "rollouts_stopped" not in evaluation.tags and not run.delete_artifact(
                f"evaluation/{split}_monitor_states.npz"):
            run.set_tags({"stale_artifacts": f"evaluation/{split}_monitor_states.npz (from before re-evaluation)"})
        run.set_tags({"reevaluated": f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}: {reason}"})
        return RunSummary(run.run_id, out_dir, checkpoint, evaluation.metrics)
