"""What evaluating a run would cost here, measured before it is trained (a campaign's budget counts
its evaluations, and a 3D domain's rollouts can cost as much as its training).

`evaluation_cost` times, on the split the run evaluates: the network's prediction step on ground-truth
windows of each evaluated trajectory (neighbour search included), multiplied by the rollout steps `evaluate`
would take; one batch of one-step windows, scaled to the configured windows; and one MMD + optimal-transport
call on the largest cloud, scaled to the configured distribution steps (by particles squared for the smaller
clouds). The weights are the untrained ones: the cost of a step does not depend on them, only on the graph,
and ground-truth frames give the graph of a rollout that tracks the data. So the figure is the cost of whole
rollouts that stay close to the ground truth, eager: a monitor's stop makes a rollout shorter, a collapsing
one costs more a step (reports/NOTES.md), a compiled rollout network (`eval.compile`) less.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from gns_bench.config import EvalConfig
from gns_bench.data.format import KINEMATIC_PARTICLE_TYPE, Trajectory
from gns_bench.evaluate import metrics
from gns_bench.evaluate.evaluate import one_step_mse
from gns_bench.model.precision import dtype_of, network_dtype

FRAMES_PER_TRAJECTORY = 3  # prediction steps timed on each trajectory (early, middle, late), after a warm-up


@dataclass(frozen=True)
class EvaluationCost:
    rollout_seconds: float  # every evaluated trajectory rolled out to its configured length
    rollout_steps: int
    one_step_seconds: float
    distribution_seconds: float  # MMD and OT at the configured steps

    @property
    def seconds(self) -> float:
        return self.rollout_seconds + self.one_step_seconds + self.distribution_seconds


def _rollout_length(trajectory: Trajectory, config: EvalConfig, w: int) -> int:
    available = trajectory.num_steps - w
    return available if config.rollout_steps is None else min(config.rollout_steps, available)


@torch.no_grad()
def evaluation_cost(simulator, trajectories: list[Trajectory], config: EvalConfig,
                    device: torch.device | str = "cpu") -> EvaluationCost:
    """The seconds `evaluate(simulator, trajectories, config)` would spend here, measured on the data
    (see the module's docstring for what is timed and what is not)."""
    if config.max_trajectories is not None:
        trajectories = trajectories[: config.max_trajectories]
    w = simulator.input_sequence_length
    trajectories = [t for t in trajectories if _rollout_length(t, config, w) > 0]
    if not trajectories:
        return EvaluationCost(0.0, 0, 0.0, 0.0)
    simulator.eval()
    rollout_seconds, rollout_steps = 0.0, 0
    rolled_out = trajectories if "rollout" in config.metrics else []  # `eval.metrics`: only what is computed
    with network_dtype(simulator, dtype_of(config.precision)):
        for index, trajectory in enumerate(rolled_out):
            length = _rollout_length(trajectory, config, w)
            frames = np.linspace(w, w + length - 1, FRAMES_PER_TRAJECTORY).round().astype(int).tolist()
            if index == 0:  # warm-up: allocation, first-call dispatch
                _time_predictions(simulator, trajectory, frames[:1], config.precision, device)
            rollout_seconds += _time_predictions(simulator, trajectory, frames, config.precision, device) * length
            rollout_steps += length
    one_step = _one_step_seconds(simulator, trajectories, config, device) if "one_step" in config.metrics else 0.0
    distribution = (_distribution_seconds(trajectories, config, simulator.radius)
                    if "distribution" in config.metrics else 0.0)
    return EvaluationCost(rollout_seconds, rollout_steps, one_step, distribution)


def _time_predictions(simulator, trajectory: Trajectory, frames: list[int], precision: str, device) -> float:
    """Mean seconds of one prediction step (neighbour search included) from the ground-truth window ending
    before each of `frames`."""
    w, dtype = simulator.input_sequence_length, dtype_of(precision)
    position = torch.from_numpy(trajectory.position).to(device, dtype)
    types = torch.from_numpy(trajectory.particle_type).to(device)
    context = (torch.from_numpy(trajectory.step_context).to(device, dtype)
               if trajectory.step_context is not None else None)
    started = time.perf_counter()
    for frame in frames:
        window = position[frame - w: frame].transpose(0, 1).contiguous()
        step_context = context[frame - 1: frame] if context is not None else None
        simulator.predict_next_position(window, types, None, step_context, precision=precision)
    return (time.perf_counter() - started) / len(frames)


TIMED_WINDOWS = 16  # one-step windows timed on the first trajectory


def _one_step_seconds(simulator, trajectories: list[Trajectory], config: EvalConfig, device) -> float:
    """One batch of windows on the first trajectory, scaled to every trajectory's windows (by particles)."""
    first = trajectories[0]
    w = simulator.input_sequence_length
    started = time.perf_counter()
    one_step_mse(simulator, first, TIMED_WINDOWS, device, config.precision)
    per_window_particle = (time.perf_counter() - started) / (min(TIMED_WINDOWS, first.num_steps - w)
                                                            * first.num_particles)
    windows = [t.num_steps - w if config.one_step_windows is None else min(config.one_step_windows, t.num_steps - w)
               for t in trajectories]
    return per_window_particle * sum(n * t.num_particles for n, t in zip(windows, trajectories, strict=True))


def _distribution_seconds(trajectories: list[Trajectory], config: EvalConfig, radius: float) -> float:
    """One MMD + OT call on the largest moving cloud (two ground-truth frames), scaled to every trajectory's
    `distribution_steps` calls by (particles / the largest's)^2."""
    if config.distribution_steps <= 0:
        return 0.0

    def cloud_size(t: Trajectory) -> int:
        moving = int((t.particle_type != KINEMATIC_PARTICLE_TYPE).sum())
        cap = config.distribution_max_particles
        return moving if cap is None else min(moving, cap)

    largest = max(trajectories, key=cloud_size)
    size = cloud_size(largest)
    if size == 0:
        return 0.0
    moving = largest.particle_type != KINEMATIC_PARTICLE_TYPE
    keep = metrics.subsample_particles(int(moving.sum()), config.distribution_max_particles)
    x, y = largest.position[-1][moving][keep], largest.position[-2][moving][keep]
    started = time.perf_counter()
    metrics.mmd(x, y, config.mmd_bandwidth_radii * radius)
    metrics.optimal_transport(x, y)
    seconds = time.perf_counter() - started
    return seconds * config.distribution_steps * sum((cloud_size(t) / size) ** 2 for t in trajectories)
