"""Evaluation on a held-out split: one-step MSE, rollout MSE, and the constant-velocity baseline."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from gns_bench.config import EvalConfig
from gns_bench.data.format import Trajectory
from gns_bench.data.windows import make_batch
from gns_bench.evaluate import metrics
from gns_bench.evaluate.rollout import Hook, RolloutResult, rollout
from gns_bench.model.simulator import LearnedSimulator, kinematic_mask

ONE_STEP_BATCH = 16  # windows per forward pass when measuring one-step error


@dataclass
class Evaluation:
    metrics: dict[str, float]
    rollouts: list[RolloutResult] = field(default_factory=list)
    per_trajectory: list[dict[str, float]] = field(default_factory=list)


@torch.no_grad()
def one_step_mse(simulator: LearnedSimulator, trajectory: Trajectory, max_windows: int | None = None,
                 device: torch.device | str = "cpu") -> float:
    """Mean over windows, moving particles and dims of (predicted - true next position)^2, no noise."""
    w = simulator.config.input_sequence_length
    frames = list(range(w - 1, trajectory.num_steps - 1))
    if max_windows is not None and len(frames) > max_windows:
        frames = [frames[i] for i in np.linspace(0, len(frames) - 1, max_windows).round().astype(int)]
    moving = ~kinematic_mask(torch.from_numpy(trajectory.particle_type))
    total, count = 0.0, 0
    for start in range(0, len(frames), ONE_STEP_BATCH):
        chunk = frames[start: start + ONE_STEP_BATCH]
        batch = make_batch([trajectory], [(0, t) for t in chunk], w).to(device)
        predicted = simulator.predict_next_position(batch.window, batch.particle_type, batch.batch, batch.context)
        error = (predicted - batch.target).double().square().reshape(len(chunk), -1, trajectory.position.shape[2])
        error = error[:, moving.to(error.device)]
        total += float(error.sum())
        count += error.numel()
    return total / count


def evaluate(simulator: LearnedSimulator, trajectories: list[Trajectory], config: EvalConfig, *,
             device: torch.device | str = "cpu", hooks: tuple[Hook, ...] = (),
             progress: bool = True) -> Evaluation:
    if config.max_trajectories is not None:
        trajectories = trajectories[: config.max_trajectories]
    results, per_traj = [], []
    for index, traj in enumerate(tqdm(trajectories, desc="evaluate", unit="traj", disable=not progress)):
        started = time.perf_counter()
        result = rollout(simulator, traj, config.rollout_steps, hooks, device)
        rollout_seconds = time.perf_counter() - started
        mask = result.moving_mask
        k = result.predicted.shape[0]
        row = {
            "trajectory": index,
            "one_step_mse": one_step_mse(simulator, traj, config.one_step_windows, device),
            "rollout_mse": metrics.rollout_mse(result.predicted, result.ground_truth[:k], mask) if k else float("nan"),
            "baseline_cv_rollout_mse": metrics.rollout_mse(
                metrics.constant_velocity_rollout(result.initial_window, result.ground_truth.shape[0]),
                result.ground_truth, mask),
            "rollout_steps": k,
            "rollout_seconds_per_step": rollout_seconds / max(k, 1),
        }
        for h, value in metrics.mse_at_horizons(result.predicted, result.ground_truth[:k], mask).items():
            row[f"mse_h{h}"] = value
        per_traj.append(row)
        results.append(result)
    summary = {}
    for key in per_traj[0]:
        if key != "trajectory":
            summary[key] = float(np.mean([row[key] for row in per_traj if key in row]))
    summary["num_trajectories"] = float(len(per_traj))
    return Evaluation(summary, results, per_traj)


def save_rollouts(evaluation: Evaluation, path: str | Path) -> Path:
    """All rollouts with their ground truth in one compressed npz (loadable without gns-bench)."""
    arrays = {}
    for i, r in enumerate(evaluation.rollouts):
        arrays[f"{i:05d}/predicted"] = r.predicted
        arrays[f"{i:05d}/ground_truth"] = r.ground_truth
        arrays[f"{i:05d}/initial_window"] = r.initial_window
        arrays[f"{i:05d}/particle_type"] = r.particle_type
    path = Path(path)
    np.savez_compressed(path, **arrays)
    return path
