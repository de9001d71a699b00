"""Evaluation on a held-out split: one-step MSE, rollout MSE, the constant-velocity baseline, and the
distributional metrics (MMD, optimal transport; paper App. B.4) and kinetic-energy error."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from gns_bench.config import EvalConfig
from gns_bench.data import free_fall
from gns_bench.data.format import KINEMATIC_PARTICLE_TYPE, Trajectory
from gns_bench.data.windows import GraphBatch, make_batch
from gns_bench.evaluate import diagnostics, metrics
from gns_bench.evaluate import registry as metric_registry
from gns_bench.evaluate.monitors import arm, default_monitors, flags
from gns_bench.evaluate.rollout import Hook, RolloutResult, rollout, static_particles
from gns_bench.model.neighbours import radius_graph, rollout_neighbours
from gns_bench.model.precision import compiled_for_inference, dtype_of, network_dtype
from gns_bench.model.simulator import LearnedSimulator, kinematic_mask
from gns_bench.progress import progress_bar

# One-step errors batch windows into one forward up to this many particles a graph (by device kind): on a CPU a
# larger graph falls out of the caches and costs more a window, on a GPU a small one is launch-bound.
ONE_STEP_PARTICLES = {"cpu": 2048, "cuda": 65536}
GRAVITY_WINDOWS = 16  # true windows per trajectory on which `one_step_gravity_ratio` asks the model
# Per-trajectory values that are NaN where they do not apply (no particle in free fall, no walls, the truth
# barely falls): their summary is the mean over the trajectories where they do.
NAN_WHERE_NOT_APPLICABLE = ("gravity_ratio", "held_gravity_ratio", "held_fall_ratio", "rollout_gravity_ratio",
                            "landing_ratio", "wall_pass_fraction", "wall_depth", "com_fall_ratio")
HELD_FALL_STEPS = 10  # how long `held_fall_ratio` rolls out a block let go from rest
HELD_FALL_WINDOWS = 4  # and from how many frames of each trajectory


@dataclass
class Evaluation:
    metrics: dict[str, float]
    rollouts: list[RolloutResult] = field(default_factory=list)
    per_trajectory: list[dict[str, float]] = field(default_factory=list)
    tags: dict[str, str] = field(default_factory=dict)  # e.g. {"ot_method": "emd"}: how a metric was computed


def distributional_metrics(result: RolloutResult, config: EvalConfig, radius: float,
                           device: torch.device | str = "cpu") -> tuple[dict[str, float], str]:
    """MMD and OT between predicted and true moving-particle clouds, averaged over `config.distribution_steps`
    evenly spaced rollout steps, plus the kinetic-energy error over every step. Returns (values, OT method)."""
    k = min(result.predicted.shape[0], result.ground_truth.shape[0])
    nan = float("nan")  # every row gets the same keys (the per-trajectory CSV needs them)
    if k == 0 or not result.moving_mask.any():
        return {"kinetic_energy_error": nan, "mmd": nan, "ot": nan, "ot_exact": nan}, ""
    scored = result.scored_mask(k)
    per_step = scored.ndim > 1  # inflow: each step compares the particles present then
    first = scored[0] if per_step and scored[0].any() else result.moving_mask  # kinetic energy: present at start
    values = {"kinetic_energy_error": metrics.kinetic_energy_error(
        result.predicted[:k][:, first], result.ground_truth[:k][:, first], result.initial_window[-1][first])}
    steps = metrics.evenly_spaced_steps(k, config.distribution_steps)
    if len(steps) == 0:
        return {**values, "mmd": nan, "ot": nan, "ot_exact": nan}, ""
    bandwidth = config.mmd_bandwidth_radii * radius
    mmds, ots, method = [], [], ""
    for step in steps:
        mask = scored[step] if per_step else scored
        x, y = result.predicted[step][mask], result.ground_truth[step][mask]
        keep = metrics.subsample_particles(x.shape[0], config.distribution_max_particles)
        x, y = x[keep], y[keep]
        mmds.append(metrics.mmd(x, y, bandwidth))
        value, method = metrics.optimal_transport(x, y)
        ots.append(value)
    values.update(mmd=float(np.mean(mmds)), ot=float(np.mean(ots)), ot_exact=float(method == "emd"))
    return values, method


class OneStepMSE(NamedTuple):
    """One-step position MSE under the two definitions evaluation logs (see `one_step_mse`); the field names
    are the metric names."""

    one_step_mse: float  # the release's `one_step_position_mse`: what the paper's table reports
    one_step_mse_moving: float  # kinematic particles left out


@torch.no_grad()
def one_step_mse(simulator: LearnedSimulator, trajectory: Trajectory, max_windows: int | None = None,
                 device: torch.device | str = "cpu", precision: str = "fp32") -> OneStepMSE:
    """Mean of (predicted - true next position)^2 over windows, particles and dims, no input noise; the
    network in `precision` (fp32, bf16 autocast, or the fp64 reference).

    `all_particles` is the release's definition (train.py, `one_step_position_mse`: one mean over every
    particle of every evaluated window, kinematic particles' unconstrained predictions included); `moving`
    leaves kinematic particles out."""
    with network_dtype(simulator, dtype_of(precision)):
        return _one_step_mse(simulator, trajectory, max_windows, device, precision)


def _one_step_mse(simulator: LearnedSimulator, trajectory: Trajectory, max_windows: int | None,
                  device: torch.device | str, precision: str) -> OneStepMSE:
    w = simulator.input_sequence_length
    frames = list(range(w - 1, trajectory.num_steps - 1))
    if max_windows is not None and len(frames) > max_windows:
        frames = [frames[i] for i in np.linspace(0, len(frames) - 1, max_windows).round().astype(int)]
    if trajectory.has_inflow:  # each window holds only the particles present at its last input frame
        sums = [_one_step_errors(simulator, trajectory.select(trajectory.active(t)), [t], w, device, precision)
                for t in frames]
        totals = np.sum(sums, axis=0)
    else:
        totals = np.asarray(_one_step_errors(simulator, trajectory, frames, w, device, precision))
    total, count, moving_total, moving_count = totals
    return OneStepMSE(total / count, moving_total / moving_count if moving_count else float("nan"))


def _one_step_errors(simulator: LearnedSimulator, trajectory: Trajectory, frames: list[int], w: int,
                     device: torch.device | str, precision: str = "fp32") -> tuple[float, int, float, int]:
    """Sum and count of squared one-step errors over windows ending at `frames`: of every particle, then
    of the moving ones."""
    moving = ~kinematic_mask(torch.from_numpy(trajectory.particle_type))
    total, count, moving_total, moving_count = 0.0, 0, 0.0, 0
    for batch, predicted in _one_step_predictions(simulator, [trajectory], [(0, t) for t in frames], device,
                                                  precision):
        windows = batch.window.shape[0] // trajectory.num_particles  # (`num_graphs` would sync a GPU)
        error = (predicted - batch.target).double().square().reshape(windows, -1, trajectory.position.shape[2])
        total += float(error.sum())
        count += error.numel()
        error = error[:, moving.to(error.device)]
        moving_total += float(error.sum())
        moving_count += error.numel()
    return total, count, moving_total, moving_count


def _one_step_predictions(simulator: LearnedSimulator, trajectories: list[Trajectory], samples: list[tuple[int, int]],
                          device: torch.device | str, precision: str) -> Iterator[tuple[GraphBatch, torch.Tensor]]:
    """The clean windows of `samples` (trajectory index, last input frame), trajectories of one particle count,
    `windows_per_forward` of them a forward, each batch with the model's next positions (the caller sets the
    network's dtype)."""
    dtype, w = dtype_of(precision), simulator.input_sequence_length
    per_forward = windows_per_forward(trajectories[0].num_particles, device)
    for start in range(0, len(samples), per_forward):
        batch = make_batch(trajectories, samples[start: start + per_forward], w).to(device)
        context = batch.context.to(dtype) if batch.context is not None else None
        yield batch, simulator.predict_next_position(batch.window.to(dtype), batch.particle_type, batch.batch,
                                                     context, precision=precision)


def windows_per_forward(num_particles: int, device: torch.device | str) -> int:
    """How many windows of `num_particles` one forward of the one-step measurements takes on `device`."""
    budget = ONE_STEP_PARTICLES.get(torch.device(device).type, ONE_STEP_PARTICLES["cpu"])
    return max(1, budget // max(num_particles, 1))


def _free_fall_frames(simulator: LearnedSimulator, trajectory: Trajectory, gravity: list[float],
                      max_windows: int) -> tuple[list[int], np.ndarray, np.ndarray]:
    """Up to `max_windows` last input frames (evenly spread) at which the ground truth has moving particles in
    free fall, with the true accelerations [T - 2, N, D] and the free-fall mask [T - 2, N] (index i: frame
    i + 1). No frames with inflow (a window holds only the particles present)."""
    w = simulator.input_sequence_length
    moving = trajectory.particle_type != KINEMATIC_PARTICLE_TYPE
    true_acc = free_fall.accelerations(trajectory.position)
    falling = free_fall.free_fall_mask(true_acc, gravity) & moving[None]
    frames = [] if trajectory.has_inflow else _frames_with(falling, w, max_windows)
    return frames, true_acc, falling


def _frames_with(mask: np.ndarray, w: int, max_windows: int) -> list[int]:
    """Up to `max_windows` last input frames (evenly spread) of a window of `w` frames at which `mask` [T - 2, N]
    (index i: frame i + 1) holds for some particle."""
    frames = [t for t in range(w - 1, mask.shape[0] + 1) if mask[t - 1].any()]
    if len(frames) > max_windows:
        frames = [frames[i] for i in np.linspace(0, len(frames) - 1, max_windows).round().astype(int)]
    return frames


def _predicted_accelerations(simulator: LearnedSimulator, trajectories: list[Trajectory],
                             samples: list[tuple[int, int]], device: torch.device | str,
                             precision: str) -> np.ndarray:
    """[len(samples), N, D] the model's accelerations on the clean windows (trajectory index, last input
    frame) of `samples`, trajectories of N particles each, as many a forward as `windows_per_forward`."""
    chunks = []
    with network_dtype(simulator, dtype_of(precision)):
        for batch, predicted in _one_step_predictions(simulator, trajectories, samples, device, precision):
            window = batch.window.double()
            chunks.append((predicted.double() - 2.0 * window[:, -1] + window[:, -2]).cpu().numpy())
    return np.concatenate(chunks).reshape(len(samples), trajectories[0].num_particles, -1)


@torch.no_grad()
def one_step_gravity_ratio(simulator: LearnedSimulator, trajectory: Trajectory, gravity: list[float],
                           max_windows: int = GRAVITY_WINDOWS, device: torch.device | str = "cpu",
                           precision: str = "fp32") -> float:
    """`diagnostics.gravity_ratio` of the model's one-step predictions on true windows: over the moving
    particles the ground truth has in free fall at a window's last frame, the predicted acceleration along g
    over the true one (up to `max_windows` windows, evenly spread over the frames that have such particles)."""
    frames, true_acc, falling = _free_fall_frames(simulator, trajectory, gravity, max_windows)
    if not frames:
        return float("nan")
    ours = _predicted_accelerations(simulator, [trajectory], [(0, t) for t in frames], device, precision)
    index = np.array(frames) - 1
    return diagnostics.gravity_ratio(ours, true_acc[index], falling[index], gravity)


@torch.no_grad()
def one_step_landing_ratio(simulator: LearnedSimulator, trajectory: Trajectory, gravity: list[float],
                           bounds: list[list[float]], max_windows: int = GRAVITY_WINDOWS,
                           device: torch.device | str = "cpu", precision: str = "fp32") -> float:
    """`diagnostics.landing_ratio` of the model's one-step predictions on true windows: over the moving
    particles landing in the ground truth at a window's last frame (moving towards the floor, near it:
    `diagnostics.landing_mask`), the predicted push beyond gravity over the true one (up to `max_windows`
    windows, evenly spread over the frames that have them). Near 0 a model lets landing material fall on: its
    rollouts pass the floor."""
    if trajectory.has_inflow:  # a window holds only the particles present
        return float("nan")
    moving = trajectory.particle_type != KINEMATIC_PARTICLE_TYPE
    landing = diagnostics.landing_mask(trajectory.position, bounds, gravity, simulator.radius, moving)
    frames = _frames_with(landing, simulator.input_sequence_length, max_windows)
    if not frames:
        return float("nan")
    ours = _predicted_accelerations(simulator, [trajectory], [(0, t) for t in frames], device, precision)
    index = np.array(frames) - 1
    return diagnostics.landing_ratio(ours, free_fall.accelerations(trajectory.position)[index], landing[index],
                                     gravity)


@torch.no_grad()
def held_gravity_ratio(simulator: LearnedSimulator, trajectory: Trajectory, gravity: list[float],
                       max_windows: int = GRAVITY_WINDOWS, device: torch.device | str = "cpu",
                       precision: str = "fp32") -> float:
    """`one_step_gravity_ratio` with the material held still: each window's frames all set to its last frame
    (every input velocity zero), as a block at rest in mid-air just let go. Over the same particles (in free
    fall there in the truth), the predicted acceleration along g over the true one. Near 1, a block the model's
    own rollout stops in mid-air falls again; near 0, rest in mid-air is a state the model never leaves."""
    frames, true_acc, falling = _free_fall_frames(simulator, trajectory, gravity, max_windows)
    if not frames:
        return float("nan")
    w = simulator.input_sequence_length
    held = [free_fall.held_still(trajectory, t, w, 1, gravity) for t in frames]  # the windows `train.held_share` adds
    ours = _predicted_accelerations(simulator, held, [(i, w - 1) for i in range(len(frames))], device, precision)
    index = np.array(frames) - 1
    return diagnostics.gravity_ratio(ours, true_acc[index], falling[index], gravity)


@torch.no_grad()
def held_fall_ratio(simulator: LearnedSimulator, trajectory: Trajectory, gravity: list[float],
                    steps: int = HELD_FALL_STEPS, max_windows: int = HELD_FALL_WINDOWS,
                    device: torch.device | str = "cpu", precision: str = "fp32") -> float:
    """A block let go from rest, rolled out: the material of a frame where every moving particle is in free
    fall (`free_fall.falling_frames`; up to `max_windows` frames, evenly spread) held still for the input window
    and let go, the model's own rollout over `steps` steps, and how far it moves the moving particles along g
    over the exact fall from rest, |g| k(k+1)/2 after k steps (a body in free fall is free of stress). Near 1 a
    block a rollout stops in mid-air falls again; 0, it stays; below 0 the model lifts it. `held_gravity_ratio`
    reads the first step only; the steps after it, whose windows hold the first small velocities, a model may
    answer quite differently (a push back up, as a resting pile pushes back), and this counts them all."""
    frames = free_fall.falling_frames(trajectory, gravity)
    if not len(frames):
        return float("nan")
    if len(frames) > max_windows:
        frames = frames[np.linspace(0, len(frames) - 1, max_windows).round().astype(int)]
    w = simulator.input_sequence_length
    moving = trajectory.particle_type != KINEMATIC_PARTICLE_TYPE
    g = np.asarray(gravity, dtype=np.float64)
    down = g / np.linalg.norm(g)
    falls = []
    for frame in frames:
        held = free_fall.held_still(trajectory, int(frame), w, steps, gravity)
        result = rollout(simulator, held, steps, device=device, precision=precision)
        moved = result.predicted[-1][moving].astype(np.float64) - held.position[w - 1][moving]
        falls.append(float((moved @ down).mean()))
    return float(np.mean(falls) / (np.linalg.norm(g) * steps * (steps + 1) / 2))


def physical_diagnostics(result: RolloutResult, bounds: list[list[float]], walls: bool,
                         gravity: list[float] | None, radius: float) -> dict[str, float]:
    """The rollout's `diagnostics`: gravity ratio along the rollout, the share of particles through a wall and
    how far beyond it they get (with walls), the centre of mass against the truth's (its fall counted where the
    truth falls at least R)."""
    moving, nan = result.moving_mask, float("nan")
    k = min(result.predicted.shape[0], result.ground_truth.shape[0])
    predicted, truth = result.predicted[:k], result.ground_truth
    row = {"rollout_gravity_ratio": (diagnostics.rollout_gravity_ratio(result.initial_window, predicted, truth, moving,
                                                                      gravity) if gravity is not None else nan),
           "wall_pass_fraction": diagnostics.wall_pass_fraction(predicted, bounds, moving) if walls else nan,
           "wall_depth": diagnostics.wall_depth(predicted, bounds, moving, radius) if walls else nan}
    row.update(diagnostics.centre_of_mass_errors(result.initial_window, predicted, truth, moving, gravity, radius))
    return row


def rollout_errors(result: RolloutResult, num_frames: int) -> dict[str, float]:
    """A rollout's position MSEs, of a trajectory of `num_frames` frames:

    - `rollout_mse`, the paper's, as the release computes it (train.py, `get_rollout_estimator_fn`): the mean
      over its `sequence_length - 6` steps, every particle (kinematic ones follow the data: error 0) and dim;
    - `baseline_cv_rollout_mse`: constant-velocity extrapolation scored the same way (kinematic particles on
      their true paths too), and `baseline_cv_same_steps_mse` over the steps the GNS rollout covered, the
      like-for-like baseline when a monitor stopped it;
    - `rollout_mse_moving`: moving particles only, over every predicted step (gns-bench before it followed the release);
    - `rollout_mse_held` and `mse_h<h>_held`: the rollout MSE over the same steps as `baseline_cv_rollout_mse`
      and the MSE at each fixed horizon, with a stopped rollout counted rather than cut short: its moving
      particles held where the stop left them for the steps it did not run (`metrics.held_rollout`). Equal to
      `rollout_mse` and `mse_h<h>` for a rollout that ran to the end.
    NaN where the rollout predicted nothing."""
    k, truth, nan = result.predicted.shape[0], result.ground_truth, float("nan")
    window = result.initial_window.shape[0]
    paper_steps = min(truth.shape[0], num_frames - window - 1)
    kp = min(k, paper_steps)
    scored = result.scored_mask(truth.shape[0])
    constant_velocity = _paper_view(metrics.constant_velocity_rollout(result.initial_window, truth.shape[0]),
                                    truth, scored)
    held = metrics.held_rollout(result.predicted, result.initial_window, truth.shape[0])
    held[k:] = _paper_view(held[k:], truth[k:], scored[k:] if scored.ndim > 1 else scored)  # kinematic: on truth
    horizons = metrics.mse_at_horizons(held, truth, scored)
    return {
        "rollout_mse": metrics.rollout_mse(result.predicted[:kp], truth[:kp]) if kp else nan,
        "baseline_cv_rollout_mse": metrics.rollout_mse(constant_velocity[:paper_steps], truth[:paper_steps]),
        "baseline_cv_same_steps_mse": metrics.rollout_mse(constant_velocity[:kp], truth[:kp]) if kp else nan,
        "rollout_mse_moving": metrics.rollout_mse(result.predicted, truth[:k], result.scored_mask(k)) if k else nan,
        "rollout_mse_held": metrics.rollout_mse(held[:paper_steps], truth[:paper_steps]),
        **{f"mse_h{h}_held": value for h, value in horizons.items()},
    }


def _paper_view(rollout: np.ndarray, truth: np.ndarray, scored: np.ndarray) -> np.ndarray:
    """`rollout` [K, N, D] with every particle that is not scored (kinematic, or not yet in an inflow scene)
    on its true path, as the release's rollout puts kinematic particles: their error counts as 0."""
    keep = scored if scored.ndim > 1 else np.broadcast_to(scored, rollout.shape[:2])
    return np.where(keep[..., None], rollout, truth)


def evaluate(simulator: LearnedSimulator, trajectories: list[Trajectory], config: EvalConfig, *,
             device: torch.device | str = "cpu", hooks: tuple[Hook, ...] = (),
             progress: bool = True, bounds: list[list[float]] | None = None,
             gravity: list[float] | None = None, walls: bool = True) -> Evaluation:
    """Roll out each trajectory and measure it; `metrics` holds the means over trajectories of every
    per-trajectory value (`ot_exact`: 1 since OT became exact EMD at every size; below 1 only in runs
    evaluated before, when large clouds got a Sinkhorn divergence).

    bounds: the scene's walls when they are not the training data's (a larger arena). gravity (per stored
    frame squared, the dataset's metadata) and walls (whether the bounds are walls) feed the physical
    diagnostics (`physical_diagnostics`, `one_step_gravity_ratio`, `one_step_landing_ratio`); without gravity
    its diagnostics are NaN."""
    if config.max_trajectories is not None:
        trajectories = trajectories[: config.max_trajectories]
    wanted = set(config.metrics)
    if "rollout" not in wanted:  # one-step errors only: nothing to roll out
        return _one_step_only(simulator, trajectories, config, device, progress)
    results, per_traj, methods, stops, flagged = [], [], set(), [], []
    rolled_out_by, compile_choice = rollout_model(simulator, trajectories, config, device)
    skin, skin_choice = neighbour_skin(simulator, trajectories, config, device)
    for index, traj in enumerate(progress_bar(trajectories, desc="evaluate", unit="traj", disable=not progress)):
        monitors = arm(health_monitors(simulator, traj, config.rollout_steps, bounds, config.monitors),
                       config.stop_on)
        w = simulator.input_sequence_length
        length = traj.num_steps - w if config.rollout_steps is None else min(config.rollout_steps, traj.num_steps - w)
        steps_bar = progress_bar(total=length, desc=f"trajectory {index} rollout", unit="step", leave=False,
                         disable=not progress)  # within a trajectory: steps/s and ETA
        run_hooks = (*hooks, lambda state, bar=steps_bar: bar.update(1), *monitors)
        started = time.perf_counter()
        result = rollout(rolled_out_by, traj, config.rollout_steps, run_hooks, device,
                         neighbour_skin=skin, precision=config.precision, bounds=bounds,
                         moving_only=config.moving_only, static_encodings=config.static_encodings)
        rollout_seconds = time.perf_counter() - started
        steps_bar.set_description(f"trajectory {index} one-step and distributional metrics")
        if result.stopped_by is not None:
            stops.append(f"trajectory {index}: {result.stop_reason}")
        trips = flags(monitors)  # monitors outside `stop_on`: the rollout ran on past them
        if trips:
            flagged.append(f"trajectory {index}: " + ", ".join(trip.reason for trip in trips))
        k = result.predicted.shape[0]
        trip_steps = [trip.step for trip in trips]
        row = {
            "trajectory": index,
            **(one_step_mse(simulator, traj, config.one_step_windows, device)._asdict()
               if "one_step" in wanted else {}),
            **rollout_errors(result, traj.num_steps),
            "rollout_steps": k,
            "rollout_seconds_per_step": rollout_seconds / max(k, 1),
            "rollout_stopped": float(result.stopped_at is not None),
            "rollout_flagged": float(bool(trips)),
            "steps_before_trip": float(diagnostics.steps_before_trip(k, result.stopped_at, trip_steps)),
        }
        if "diagnostics" in wanted:
            for name, ratio in (("gravity_ratio", one_step_gravity_ratio), ("held_gravity_ratio", held_gravity_ratio),
                                ("held_fall_ratio", held_fall_ratio)):
                row[name] = (ratio(simulator, traj, gravity, device=device, precision=config.precision)
                             if gravity is not None else float("nan"))
            walls_at = bounds if bounds is not None else simulator.bounds.tolist()
            row["landing_ratio"] = (one_step_landing_ratio(simulator, traj, gravity, walls_at, device=device,
                                                           precision=config.precision)
                                    if gravity is not None and walls else float("nan"))
            row.update(physical_diagnostics(result, walls_at, walls, gravity, simulator.radius))
        if traj.step_context is not None:  # e.g. the friction angle: error against it (held-out intervals)
            row["context"] = float(traj.step_context[0, 0])
        row.update(metric_registry.compute_all(result))  # metrics of one's own (evaluate/registry.py)
        horizons = metrics.mse_at_horizons(result.predicted, result.ground_truth[:k], result.scored_mask(k))
        row.update({f"mse_h{h}": value for h, value in horizons.items()})
        if "distribution" in wanted:
            distributional, method = distributional_metrics(result, config, simulator.radius, device)
            row.update(distributional)
            if method:
                methods.add(method)
        steps_bar.close()
        per_traj.append(row)
        results.append(result)
    tags = {"ot_method": ",".join(sorted(methods))} if methods else {}
    if compile_choice:  # eval.compile = "auto": what the probe chose, and its timings
        tags["rollout_compile"] = compile_choice
    if skin_choice:  # eval.neighbour_skin = "auto": likewise
        tags["neighbour_skin"] = skin_choice
    if stops:  # the report shows where monitors stopped rollouts
        tags["rollouts_stopped"] = "; ".join(stops)[:5000]
    if flagged:  # and where they flagged the ones that ran on
        tags["rollouts_flagged"] = "; ".join(flagged)[:5000]
    return Evaluation(summarise(per_traj), results, per_traj, tags)


def summarise(per_trajectory: list[dict[str, float]]) -> dict[str, float]:
    """The means over trajectories of every per-trajectory value (a key only some trajectories reach too:
    `mse_h100` of the rollouts that got to step 100), NaN-where-not-applicable values over those where they
    apply, and the number of trajectories."""
    summary = {}
    for key in dict.fromkeys(key for row in per_trajectory for key in row):
        if key not in ("trajectory", "context"):
            values = [row[key] for row in per_trajectory if key in row]
            applicable = [v for v in values if np.isfinite(v)] if key in NAN_WHERE_NOT_APPLICABLE else values
            summary[key] = float(np.mean(applicable)) if applicable else float("nan")
    summary["num_trajectories"] = float(len(per_trajectory))
    return summary


def _one_step_only(simulator: LearnedSimulator, trajectories: list[Trajectory], config: EvalConfig,
                   device: torch.device | str, progress: bool) -> Evaluation:
    """`eval.metrics = ["one_step"]`: the one-step MSEs of each trajectory, and no rollout."""
    rows = [{"trajectory": index, **one_step_mse(simulator, traj, config.one_step_windows, device)._asdict()}
            for index, traj in enumerate(progress_bar(trajectories, desc="evaluate (one-step)", unit="traj",
                                              disable=not progress))]
    return Evaluation(summarise(rows), [], rows, {})


def neighbour_skin(simulator: LearnedSimulator, trajectories: list[Trajectory], config: EvalConfig,
                   device: torch.device | str = "cpu") -> tuple[float, str]:
    """The Verlet skin the rollouts use, and what an "auto" probe chose ("" when the skin was given): the probe
    walks the first trajectory's true frames through each candidate (`autotune.choose_neighbour_skin`)."""
    if config.neighbour_skin != "auto":
        return float(config.neighbour_skin), ""
    first = trajectories[0] if trajectories else None
    if first is None or not simulator.uses_edges or first.has_inflow:
        return 0.0, "none (nothing to probe: no edges, an inflow scene, or no trajectory)"
    from gns_bench import autotune

    finder, truth = neighbour_finders(simulator, first, device, dtype_of(config.precision))
    choice = autotune.choose_neighbour_skin(finder, truth, simulator.radius)
    return choice.skin, choice.describe()


def neighbour_finders(simulator: LearnedSimulator, trajectory: Trajectory, device: torch.device | str = "cpu",
                      dtype: torch.dtype = torch.float32) -> tuple[Callable[[float], Callable], torch.Tensor]:
    """(make_finder, the true frames from the last input frame on): `make_finder(skin)` is what a rollout of
    `trajectory` would search its edges with at that skin (positions [N, D] -> edges [2, E])."""
    w = simulator.input_sequence_length
    truth = torch.from_numpy(trajectory.position[w - 1:]).to(device, dtype)
    static = static_particles(torch.from_numpy(trajectory.position).to(device),
                              torch.from_numpy(trajectory.particle_type).to(device))
    backend, radius, self_edges = simulator.neighbour_backend, simulator.radius, simulator.self_edges

    def finder(skin: float) -> Callable[[torch.Tensor], torch.Tensor]:
        found = rollout_neighbours(radius, backend, self_edges, skin, truth[0], static)
        return found if found is not None else (
            lambda position: radius_graph(position, radius, backend=backend, self_edges=self_edges))

    return finder, truth


def rollout_model(simulator: LearnedSimulator, trajectories: list[Trajectory], config: EvalConfig,
                  device: torch.device | str = "cpu") -> tuple[LearnedSimulator, str]:
    """What the rollouts run: the simulator, or its compiled, frozen copy (`eval.compile`). For "auto", a
    short probe on the first trajectory's first step here decides whether compiling pays over all the
    rollouts' steps (`autotune.choose_rollout_compile`); the second value describes that choice ("" when
    nothing was auto)."""
    if config.compile is True:
        return compiled_for_inference(simulator), ""
    if config.compile is False or not trajectories or getattr(simulator, "network", None) is None:
        return simulator, ("" if config.compile is False else "eager (nothing to compile)")
    from gns_bench import autotune

    first, w = trajectories[0], simulator.input_sequence_length
    window = torch.from_numpy(first.position[:w]).transpose(0, 1).contiguous().to(device)
    types = torch.from_numpy(first.particle_type).to(device)
    context = (torch.from_numpy(first.step_context[w - 1: w]).to(device) if first.step_context is not None
               else None)
    steps = sum(t.num_steps - w if config.rollout_steps is None else min(config.rollout_steps, t.num_steps - w)
                for t in trajectories)

    @torch.no_grad()
    def step(model: LearnedSimulator) -> None:
        model.predict_next_position(window, types, None, context, precision=config.precision)

    choice, compiled = autotune.choose_rollout_compile(simulator, step, config.precision, first.num_particles,
                                                       torch.device(device), steps)
    if not choice.compile:
        return simulator, choice.describe()
    return (compiled if compiled is not None else compiled_for_inference(simulator)), choice.describe()


def health_monitors(simulator: LearnedSimulator, trajectory: Trajectory, num_steps: int | None,
                    bounds: list[list[float]] | None = None, which: bool | list[str] = True) -> list:
    """The monitors `which` names (`eval.monitors`: true for the default four, false for none) for one
    trajectory, with its ground-truth kinetic energy and positions as the references (in inflow scenes
    particles not yet present follow the data, in the rollout as in the reference)."""
    if which is False or (isinstance(which, list) and not which):
        return []
    w = simulator.input_sequence_length
    truth = trajectory.position[w - 1: w + (num_steps if num_steps is not None else trajectory.num_steps)]
    moving = trajectory.particle_type != KINEMATIC_PARTICLE_TYPE
    reference = metrics.kinetic_energy(truth[1:], truth[0], moving) if len(truth) > 1 else None
    window = torch.from_numpy(trajectory.position[:w]).transpose(0, 1)
    monitors = default_monitors(bounds if bounds is not None else simulator.bounds.tolist(), simulator.radius,
                                window, torch.from_numpy(moving), reference, truth[1:])
    return monitors if which is True else [m for m in monitors if m.name in which]


def save_rollouts(evaluation: Evaluation, path: str | Path) -> Path:
    """All rollouts with their ground truth in one compressed npz (loadable without gns-bench)."""
    arrays = {}
    for i, r in enumerate(evaluation.rollouts):
        arrays[f"{i:05d}/predicted"] = r.predicted
        arrays[f"{i:05d}/ground_truth"] = r.ground_truth
        arrays[f"{i:05d}/initial_window"] = r.initial_window
        arrays[f"{i:05d}/particle_type"] = r.particle_type
        if r.birth_step is not None:
            arrays[f"{i:05d}/birth_step"] = r.birth_step
        if r.stopped_at is not None:  # where a health monitor stopped it, and why (pictures mark it)
            arrays[f"{i:05d}/stopped_at"] = np.array(r.stopped_at)
            arrays[f"{i:05d}/stop_reason"] = np.array(r.stop_reason or "")
    path = Path(path)
    np.savez_compressed(path, **arrays)
    return path
