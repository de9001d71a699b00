"""Rollouts (paper Sec. 3.1, 4.4): start from the first W frames and feed predictions back.

Kinematic particles take their positions from the ground truth at every step. Hooks see each new
state and may stop a rollout by raising `RolloutStopped` (health monitors build on this).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from gns_bench.data.format import Trajectory
from gns_bench.evaluate.result import RolloutResult, RolloutStopped
from gns_bench.model.neighbours import rollout_neighbours
from gns_bench.model.precision import dtype_of, network_dtype
from gns_bench.model.simulator import LearnedSimulator, kinematic_mask
from gns_bench.model.static_encodings import StaticEncodings


@dataclass
class RolloutState:
    step: int  # index of the predicted frame within the rollout (0 = first prediction)
    frame: int  # index of that frame in the trajectory
    position: torch.Tensor  # [N, D] the new positions
    window: torch.Tensor  # [N, W, D] the window they were predicted from
    present: torch.Tensor | None = None  # [N] bool, inflow only: the particles in the scene (the others wait)


Hook = Callable[[RolloutState], None]


def static_particles(truth: torch.Tensor, particle_type: torch.Tensor) -> torch.Tensor:
    """[N] bool: the kinematic particles that never move over the frames `truth` [T, N, D] (fixed boundaries)."""
    return (truth == truth[:1]).all(dim=2).all(dim=0) & kinematic_mask(particle_type)


@torch.no_grad()
def rollout(simulator: LearnedSimulator, trajectory: Trajectory, num_steps: int | None = None,
            hooks: Sequence[Hook] = (), device: torch.device | str = "cpu",
            neighbour_skin: float = 0.0, precision: str = "fp32", reuse_static_edges: bool = True,
            bounds: Sequence[Sequence[float]] | None = None, moving_only: bool = True,
            static_encodings: bool = True) -> RolloutResult:
    """Roll out from the first W frames; every option below gives the same edges as a fresh search.

    neighbour_skin > 0: Verlet neighbour lists, rebuilt only when particles moved skin / 2.
    reuse_static_edges: edges among particles that never move (fixed boundaries) are found once.
    moving_only: a simulator that offers it (`predicts_moving_only`) skips the work of the kinematic particles,
    whose positions come from the data (the same positions up to the rounding of smaller matrix products).
    static_encodings: a simulator that offers it (`caches_static_encodings`) encodes the particles that never
    move, and the edges among them, at the first step only (`model/static_encodings.py`; the same up to the
    same rounding).
    precision "bf16" / "fp64": autocast the network to bf16, or run it in float64 (a reference).
    bounds: the scene's walls, when they are not the training data's (a larger arena).
    Inflow (`trajectory.birth_step`): a particle enters the graph at its birth frame with the window of
    its prescribed path; before that it follows the data, like a kinematic particle, and sees nothing.
    """
    w = simulator.input_sequence_length
    available = trajectory.num_steps - w
    num_steps = available if num_steps is None else min(num_steps, available)
    dtype = dtype_of(precision)
    truth = torch.from_numpy(trajectory.position).to(device, dtype)  # [T, N, D]
    particle_type = torch.from_numpy(trajectory.particle_type).to(device)
    kinematic = kinematic_mask(particle_type)[:, None]
    context = (torch.from_numpy(trajectory.step_context).to(device, dtype)
               if trajectory.step_context is not None else None)
    scene_bounds = None if bounds is None else torch.tensor(bounds, dtype=dtype, device=device)
    birth = (torch.from_numpy(trajectory.birth_step).to(device) if trajectory.has_inflow else None)
    window = truth[:w].transpose(0, 1).contiguous()  # [N, W, D]
    predicted, stopped_at, reason, stopped_by = [], None, None, None
    static = static_particles(truth, particle_type)
    neighbours = None  # inflow: the particle set changes, a fresh search every step over the particles present
    if birth is None and simulator.uses_edges:
        neighbours = rollout_neighbours(simulator.radius, simulator.neighbour_backend, simulator.self_edges,
                                        neighbour_skin, truth[0], static if reuse_static_edges else None)
    skip = {"moving_only": True} if moving_only and getattr(simulator, "predicts_moving_only", False) else {}
    if (static_encodings and birth is None and getattr(simulator, "caches_static_encodings", False)
            and bool(static.any()) and not bool(static.all())):
        skip["static_encodings"] = StaticEncodings(static)
    with network_dtype(simulator, dtype):
        for step in range(num_steps):
            frame = w + step
            step_context = context[frame - 1: frame] if context is not None else None
            present = None
            if birth is None:
                edges = neighbours(window[:, -1]) if neighbours is not None else None
                next_position = simulator.predict_next_position(window, particle_type, None, step_context, edges,
                                                                scene_bounds, precision, **skip)
                next_position = torch.where(kinematic, truth[frame], next_position)
            else:
                present = birth <= frame - 1  # in the scene at the last input frame
                index = present.nonzero()[:, 0]
                sub_window = window.index_select(0, index)
                moved = simulator.predict_next_position(sub_window, particle_type.index_select(0, index), None,
                                                        step_context, None, scene_bounds, precision, **skip)
                next_position = truth[frame].clone()  # absent and kinematic particles follow the data
                keep = ~kinematic[index, 0]
                next_position[index[keep]] = moved[keep]
            try:
                for hook in hooks:
                    hook(RolloutState(step, frame, next_position, window, present))
            except RolloutStopped as stop:
                stopped_at, reason, stopped_by = step, stop.reason, stop
                break
            predicted.append(next_position)
            window = torch.cat([window[:, 1:], next_position[:, None]], dim=1)
    dim = trajectory.position.shape[2]
    stacked = (torch.stack(predicted).float().cpu().numpy() if predicted
               else np.zeros((0, trajectory.num_particles, dim), dtype=np.float32))
    return RolloutResult(stacked, trajectory.position[w: w + num_steps], trajectory.position[:w],
                         trajectory.particle_type, stopped_at, reason, stopped_by,
                         trajectory.birth_step if trajectory.has_inflow else None)
