"""The stress tests of a trained model (the paper's Sec. 5.3 and App. C.7), as functions of a simulator
and trajectories: each returns a `StressResult` of scalar metrics, curves over rollout steps and the
monitors that tripped. Where the scenes come from (dataset variants) is `stress/run.py`'s business.

- horizon: rollouts far beyond the training sequence length (the paper's 8x), error against time, the
  step where a monitor stopped it, and for rigid bodies the drift of pairwise distances (App. C.7);
- precision: the same rollouts in fp64 (the reference), fp32 and bf16, and how they diverge;
- perturbation: the growth of a small initial position perturbation in the model, against the same
  perturbation's growth in the ground-truth solver;
- scale: the model on scenes with many times the training particle count, in larger arenas.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Sequence

import numpy as np

from gns_bench.data.format import RIGID_PARTICLE_TYPE, Trajectory
from gns_bench.evaluate import metrics
from gns_bench.evaluate.evaluate import health_monitors, one_step_mse
from gns_bench.evaluate.result import StressResult
from gns_bench.evaluate.rollout import RolloutResult, rollout
from gns_bench.model.simulator import LearnedSimulator

ONE_STEP_WINDOWS = 50  # windows per trajectory for the one-step error of each precision


def per_step_mse(result: RolloutResult, length: int) -> np.ndarray:
    """[length] MSE of the scored particles at each rollout step; NaN after a monitor stopped it."""
    out = np.full(length, np.nan)
    k = min(result.predicted.shape[0], result.ground_truth.shape[0], length)
    if k == 0:
        return out
    mask = result.scored_mask(k)
    error = np.square(result.predicted[:k].astype(np.float64) - result.ground_truth[:k]).sum(-1)  # [K, N]
    if mask.ndim == 1:
        out[:k] = error[:, mask].mean(1) / result.predicted.shape[2]
    else:
        out[:k] = [(error[i][mask[i]].mean() if mask[i].any() else np.nan) / result.predicted.shape[2]
                   for i in range(k)]
    return out


def rms_distance(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """[K] root-mean-square distance between two runs [K, N, D] of the same particles (mask [N])."""
    return np.sqrt(np.square(a[:, mask].astype(np.float64) - b[:, mask]).sum(-1).mean(-1))


def growth_rate(distance: np.ndarray) -> float:
    """Least-squares slope of log(distance) per step over the finite, positive part (the error growth rate;
    1 / rate steps multiply a perturbation by e)."""
    steps = np.arange(len(distance))
    ok = np.isfinite(distance) & (distance > 0)
    if ok.sum() < 2:
        return float("nan")
    return float(np.polyfit(steps[ok], np.log(distance[ok]), 1)[0])


def _stack(curves: list[np.ndarray]) -> list[float]:
    """Mean over trajectories of per-step curves (NaN-aware: a stopped rollout leaves the mean)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN steps stay NaN
        return np.nanmean(np.stack(curves), axis=0).tolist()


def _run(simulator: LearnedSimulator, traj: Trajectory, steps: int | None, device: str, *,
         precision: str = "fp32", bounds: list[list[float]] | None = None, monitors: bool = True) -> RolloutResult:
    hooks = health_monitors(simulator, traj, steps, bounds) if monitors else []
    return rollout(simulator, traj, steps, hooks, device, precision=precision, bounds=bounds)


def _trip(label: str, index: int, result: RolloutResult) -> list[str]:
    return [f"{label} trajectory {index}: {result.stop_reason}"] if result.stopped_at is not None else []


def horizon(simulator: LearnedSimulator, trajectories: Sequence[Trajectory], training_length: int, *,
            steps: int | None = None, device: str = "cpu", label: str = "long") -> StressResult:
    """Roll out trajectories longer than the training ones; error over time and the stable horizon."""
    out = StressResult("horizon")
    w = simulator.input_sequence_length
    length = max(t.num_steps - w for t in trajectories) if steps is None else steps
    errors, drifts, truth_drifts, stable = [], [], [], []
    for i, traj in enumerate(trajectories):
        result = _run(simulator, traj, length, device)
        errors.append(per_step_mse(result, length))
        out.trips += _trip(label, i, result)
        stable.append(length if result.stopped_at is None else result.stopped_at)
        rigid = traj.particle_type == RIGID_PARTICLE_TYPE
        if rigid.sum() >= 2 and result.predicted.shape[0]:
            start = result.initial_window[-1:]  # drift since the rollout began (metrics.rigidity_drift)
            drift = np.full(length, np.nan)
            drift[: result.predicted.shape[0]] = metrics.rigidity_drift(
                np.concatenate([start, result.predicted]), rigid)[1:]
            drifts.append(drift)
            truth = np.full(length, np.nan)
            truth[: min(length, len(result.ground_truth))] = metrics.rigidity_drift(
                np.concatenate([start, result.ground_truth[:length]]), rigid)[1:]
            truth_drifts.append(truth)
    out.curves["mse"] = _stack(errors)
    if drifts:
        out.curves["rigidity_drift"] = _stack(drifts)
        out.curves["rigidity_drift_truth"] = _stack(truth_drifts)
        out.metrics["rigidity_drift_final"] = float(np.nanmean([d[np.isfinite(d)][-1] for d in drifts]))
    mse = np.asarray(out.curves["mse"])
    out.metrics.update(
        steps=float(length), training_length=float(training_length), horizon_factor=length / training_length,
        stable_steps=float(min(stable)), stable_factor=min(stable) / training_length,
        mse_at_training_length=float(np.nanmean(mse[:training_length])), mse_full=float(np.nanmean(mse)),
        stopped=float(len(out.trips)))
    return out


def precision(simulator: LearnedSimulator, trajectories: Sequence[Trajectory], precisions: Sequence[str], *,
              steps: int | None = None, device: str = "cpu") -> StressResult:
    """The same rollouts in several precisions; divergence from the first one given (fp64 on CPU)."""
    out = StressResult("precision")
    reference_name = precisions[0]
    w = simulator.input_sequence_length
    length = max(t.num_steps - w for t in trajectories) if steps is None else steps
    results: dict[str, list[RolloutResult]] = {}
    seconds: dict[str, float] = {}
    for name in precisions:
        started = time.perf_counter()
        results[name] = [_run(simulator, t, length, device, precision=name) for t in trajectories]
        seconds[name] = time.perf_counter() - started
        for i, r in enumerate(results[name]):
            out.trips += _trip(name, i, r)
    for name in precisions:
        out.metrics[f"one_step_mse_{name}"] = float(np.mean([  # moving particles, as the rollout curves
            one_step_mse(simulator, t, ONE_STEP_WINDOWS, device, name).one_step_mse_moving
            for t in trajectories]))
        out.curves[f"mse_{name}"] = _stack([per_step_mse(r, length) for r in results[name]])
        out.metrics[f"rollout_mse_{name}"] = float(np.nanmean(out.curves[f"mse_{name}"]))
        out.metrics[f"seconds_{name}"] = seconds[name]
        if name == reference_name:
            continue
        divergence = []
        for r, ref in zip(results[name], results[reference_name], strict=True):
            k = min(r.predicted.shape[0], ref.predicted.shape[0])
            d = np.full(length, np.nan)
            d[:k] = rms_distance(r.predicted[:k], ref.predicted[:k], r.moving_mask)
            divergence.append(d)
        out.curves[f"divergence_{name}"] = _stack(divergence)
        curve = np.asarray(out.curves[f"divergence_{name}"])
        out.metrics[f"divergence_final_{name}"] = float(curve[np.isfinite(curve)][-1]) if np.isfinite(curve).any() \
            else float("nan")
    out.notes.append(f"divergence: RMS distance per particle from the {reference_name} rollout")
    return out


def perturb_initial_window(traj: Trajectory, std: float, window: int, rng: np.random.Generator) -> Trajectory:
    """The trajectory with each moving particle's first `window` positions shifted by one Gaussian offset
    (positions perturbed, velocities kept: what jittering the solver's initial positions does)."""
    moving = traj.particle_type != 3
    position = traj.position.copy()
    offset = rng.normal(0.0, std, size=(int(moving.sum()), position.shape[2])).astype(np.float32)
    position[:window, moving] += offset[None]
    return Trajectory(position, traj.particle_type, traj.step_context, traj.birth_step)


def perturbation(simulator: LearnedSimulator, trajectories: Sequence[Trajectory], std: float, *,
                 solver_pairs: Sequence[tuple[Trajectory, Trajectory]] = (), steps: int | None = None,
                 device: str = "cpu", seed: int = 0) -> StressResult:
    """How fast a perturbation of size `std` grows in the model, and in the solver (pairs of ground-truth
    trajectories from the same initial condition, one jittered by the same std)."""
    out = StressResult("perturbation")
    w = simulator.input_sequence_length
    length = max(t.num_steps - w for t in trajectories) if steps is None else steps
    rng = np.random.default_rng(seed)
    model_d = []
    for traj in trajectories:
        base = _run(simulator, traj, length, device, monitors=False)
        moved = _run(simulator, perturb_initial_window(traj, std, w, rng), length, device, monitors=False)
        k = min(base.predicted.shape[0], moved.predicted.shape[0])
        d = np.full(length, np.nan)
        d[:k] = rms_distance(moved.predicted[:k], base.predicted[:k], base.moving_mask)
        model_d.append(d)
    out.curves["model_distance"] = _stack(model_d)
    out.metrics["std"] = std
    out.metrics["model_growth_rate"] = growth_rate(np.asarray(out.curves["model_distance"]))
    out.metrics["model_amplification"] = float(np.nanmax(out.curves["model_distance"]) / std)
    if solver_pairs:
        solver_d = []
        for base, jittered in solver_pairs:
            n = min(base.num_steps, jittered.num_steps, w + length)
            moving = base.particle_type != 3
            d = np.full(length, np.nan)
            d[: n - w] = rms_distance(jittered.position[w:n], base.position[w:n], moving)
            solver_d.append(d)
        out.curves["solver_distance"] = _stack(solver_d)
        initial = [rms_distance(j.position[:1], b.position[:1], b.particle_type != 3)[0] for b, j in solver_pairs]
        out.metrics["solver_initial_distance"] = float(np.mean(initial))
        out.metrics["solver_growth_rate"] = growth_rate(np.asarray(out.curves["solver_distance"]))
        out.metrics["solver_amplification"] = float(np.nanmax(out.curves["solver_distance"]) / np.mean(initial))
    else:
        out.notes.append("no jittered ground truth: the solver's own sensitivity was not measured")
    return out


def scale(simulator: LearnedSimulator, scenes: dict[int, tuple[list[Trajectory], list[list[float]]]],
          training_particles: float, *, steps: int | None = None, device: str = "cpu") -> StressResult:
    """The model on larger scenes: factor -> (trajectories, their bounds). Error, stability and speed."""
    out = StressResult("scale")
    w = simulator.input_sequence_length
    for factor, (trajectories, bounds) in sorted(scenes.items()):
        length = max(t.num_steps - w for t in trajectories) if steps is None else steps
        errors, gns, baseline, scored, seconds, done = [], [], [], [], [], []
        for i, traj in enumerate(trajectories):
            started = time.perf_counter()
            result = _run(simulator, traj, length, device, bounds=bounds)
            seconds.append((time.perf_counter() - started) / max(result.predicted.shape[0], 1))
            errors.append(per_step_mse(result, length))
            # Like for like: constant velocity over the steps this GNS rollout covered, no more.
            k = int(np.sum(np.isfinite(errors[-1])))
            cv = metrics.constant_velocity_rollout(result.initial_window, k)
            gns.append(float(np.nanmean(errors[-1])) if k else np.nan)
            baseline.append(metrics.rollout_mse(cv, result.ground_truth[:k], result.scored_mask(k)) if k else np.nan)
            scored.append(k)
            done.append(length if result.stopped_at is None else result.stopped_at)
            out.trips += _trip(f"x{factor}", i, result)
        particles = float(np.mean([t.num_particles for t in trajectories]))
        out.curves[f"mse_x{factor}"] = _stack(errors)
        out.metrics.update({
            f"x{factor}/particles": particles, f"x{factor}/particle_ratio": particles / training_particles,
            f"x{factor}/rollout_mse": float(np.nanmean(gns)),
            f"x{factor}/baseline_cv_same_steps_mse": float(np.nanmean(baseline)),
            f"x{factor}/steps_scored": float(np.mean(scored)),
            f"x{factor}/seconds_per_step": float(np.mean(seconds)), f"x{factor}/steps": float(length),
            f"x{factor}/stable_steps": float(min(done))})
    stable = [f for f in scenes if out.metrics[f"x{f}/stable_steps"] >= out.metrics[f"x{f}/steps"]]
    out.metrics["largest_stable_factor"] = float(max(stable)) if stable else 0.0
    return out
