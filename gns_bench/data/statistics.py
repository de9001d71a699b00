"""Normalisation statistics of a dataset, as `metadata.json` stores them.

Velocities and accelerations are finite differences per stored frame (dt = 1 units, as in the
original release): v_t = p_t - p_{t-1}, a_t = p_{t+1} - 2 p_t + p_{t-1}. Kinematic particles are
left out: they are never predicted, and their zero motion would shrink the statistics.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from gns_bench.data.format import KINEMATIC_PARTICLE_TYPE, Trajectory


class _RunningMoments:
    """Per-dimension mean and std accumulated in float64 over batches of rows."""

    def __init__(self) -> None:
        self.count, self.total, self.total_sq = 0, 0.0, 0.0

    def add(self, rows: np.ndarray) -> None:
        rows = rows.reshape(-1, rows.shape[-1]).astype(np.float64)
        self.count += rows.shape[0]
        self.total = self.total + rows.sum(axis=0)
        self.total_sq = self.total_sq + (rows**2).sum(axis=0)

    def result(self) -> tuple[list[float], list[float]]:
        if self.count == 0:
            raise ValueError("no samples to compute statistics from")
        mean = self.total / self.count
        var = np.maximum(self.total_sq / self.count - mean**2, 0.0)
        return mean.tolist(), np.sqrt(var).tolist()


def compute_statistics(trajectories: Iterable[Trajectory]) -> dict[str, list[float]]:
    """vel_mean/std, acc_mean/std (and context_mean/std when there is a step context)."""
    vel, acc, ctx = _RunningMoments(), _RunningMoments(), _RunningMoments()
    for traj in trajectories:
        moving = traj.particle_type != KINEMATIC_PARTICLE_TYPE
        pos = traj.position[:, moving].astype(np.float64)
        if pos.shape[1] == 0:
            continue
        v = np.diff(pos, axis=0)
        a = np.diff(v, axis=0)
        if traj.birth_step is not None:  # inflow: only the motion after a particle enters counts
            birth = traj.birth_step[moving]
            v = v[np.arange(1, len(v) + 1)[:, None] > birth[None]]  # v_t = p_t - p_{t-1} with t - 1 >= birth
            a = a[np.arange(1, len(a) + 1)[:, None] > birth[None]]
        vel.add(v)
        acc.add(a)
        if traj.step_context is not None:
            ctx.add(traj.step_context)
    stats = {}
    stats["vel_mean"], stats["vel_std"] = vel.result()
    stats["acc_mean"], stats["acc_std"] = acc.result()
    if ctx.count:
        stats["context_mean"], stats["context_std"] = ctx.result()
    return stats
