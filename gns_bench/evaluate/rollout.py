"""Rollouts (paper Sec. 4.4, Knowl 4): start from the first W frames and feed predictions back.

Kinematic particles take their positions from the ground truth at every step. Hooks see each new
state and may stop a rollout by raising `RolloutStopped` (health monitors build on this).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from gns_bench.data.format import Trajectory
from gns_bench.model import features
from gns_bench.model.neighbours import StaticAwareNeighbours, VerletNeighbours
from gns_bench.model.precision import autocast
from gns_bench.model.simulator import LearnedSimulator, kinematic_mask


@dataclass
class RolloutState:
    step: int  # index of the predicted frame within the rollout (0 = first prediction)
    frame: int  # index of that frame in the trajectory
    position: torch.Tensor  # [N, D] the new positions
    window: torch.Tensor  # [N, W, D] the window they were predicted from


class RolloutStopped(Exception):
    """Raised by a hook to end a rollout early; the rollout records the step and the reason."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


Hook = Callable[[RolloutState], None]


@dataclass
class RolloutResult:
    predicted: np.ndarray  # [K, N, D] predicted frames W .. W+K-1 (fewer if stopped)
    ground_truth: np.ndarray  # [K', N, D] the true frames over the requested horizon
    initial_window: np.ndarray  # [W, N, D]
    particle_type: np.ndarray  # [N]
    stopped_at: int | None = None
    stop_reason: str | None = None
    stopped_by: RolloutStopped | None = None  # the exception a hook raised (a monitor carries its details)

    @property
    def moving_mask(self) -> np.ndarray:
        return ~kinematic_mask(torch.from_numpy(self.particle_type)).numpy()


@torch.no_grad()
def rollout(simulator: LearnedSimulator, trajectory: Trajectory, num_steps: int | None = None,
            hooks: Sequence[Hook] = (), device: torch.device | str = "cpu",
            neighbour_skin: float = 0.0, precision: str = "fp32", reuse_static_edges: bool = True
            ) -> RolloutResult:
    """Roll out from the first W frames; every option below gives the same edges as a fresh search.

    neighbour_skin > 0: Verlet neighbour lists, rebuilt only when particles moved skin / 2.
    reuse_static_edges: edges among particles that never move (fixed boundaries) are found once.
    precision "bf16": autocast the network (positions and integration stay fp32).
    """
    w = simulator.config.input_sequence_length
    available = trajectory.num_steps - w
    num_steps = available if num_steps is None else min(num_steps, available)
    truth = torch.from_numpy(trajectory.position).to(device)  # [T, N, D]
    particle_type = torch.from_numpy(trajectory.particle_type).to(device)
    kinematic = kinematic_mask(particle_type)[:, None]
    context = (torch.from_numpy(trajectory.step_context).to(device)
               if trajectory.step_context is not None else None)
    window = truth[:w].transpose(0, 1).contiguous()  # [N, W, D]
    predicted, stopped_at, reason, stopped_by = [], None, None, None
    neighbours = None
    static = (truth == truth[:1]).all(dim=2).all(dim=0) & kinematic[:, 0]
    if neighbour_skin > 0 and simulator.network.uses_edges:
        neighbours = VerletNeighbours(simulator.radius, neighbour_skin, simulator.config.neighbour_backend,
                                      simulator.config.self_edges)
    elif reuse_static_edges and simulator.network.uses_edges and bool(static.any()) and not bool(static.all()):
        neighbours = StaticAwareNeighbours(truth[0], static, simulator.radius, simulator.config.neighbour_backend,
                                           simulator.config.self_edges)
    for step in range(num_steps):
        frame = w + step
        step_context = context[frame - 1: frame] if context is not None else None
        edges = neighbours(window[:, -1]) if neighbours is not None else None
        with autocast(device, precision):
            acceleration = simulator.denormalise_acceleration(
                simulator(window, particle_type, None, step_context, edges).float())
        next_position = features.integrate(window, acceleration)
        next_position = torch.where(kinematic, truth[frame], next_position)
        try:
            for hook in hooks:
                hook(RolloutState(step, frame, next_position, window))
        except RolloutStopped as stop:
            stopped_at, reason, stopped_by = step, stop.reason, stop
            break
        predicted.append(next_position)
        window = torch.cat([window[:, 1:], next_position[:, None]], dim=1)
    dim = trajectory.position.shape[2]
    stacked = (torch.stack(predicted).cpu().numpy() if predicted
               else np.zeros((0, trajectory.num_particles, dim), dtype=np.float32))
    return RolloutResult(stacked, trajectory.position[w: w + num_steps], trajectory.position[:w],
                         trajectory.particle_type, stopped_at, reason, stopped_by)
