"""Input features and the integrator: pure functions, one per paper term.

Shapes: a window of positions is [N, W, D] (particles, time, dims), the last entry being the current
position; C = W - 1 velocities are finite differences within it (dt = 1 in stored-frame units).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class Normalisation:
    """Statistics from metadata.json, with the noise std added in quadrature (as in DeepMind's released
    code, learning_to_simulate/train.py)."""

    vel_mean: torch.Tensor  # [D]
    vel_std: torch.Tensor  # [D], sqrt(vel_std^2 + sigma^2)
    acc_mean: torch.Tensor  # [D]
    acc_std: torch.Tensor  # [D], sqrt(acc_std^2 + sigma^2)
    context_mean: torch.Tensor | None = None  # [C]
    context_std: torch.Tensor | None = None  # [C], floored at 1e-8


def velocities(window: torch.Tensor) -> torch.Tensor:
    """[N, W, D] positions -> [N, W-1, D] velocities p_t - p_{t-1}."""
    return window[:, 1:] - window[:, :-1]


def wall_distances(position: torch.Tensor, bounds: torch.Tensor, radius: float,
                   wall_range: float = 1.0) -> torch.Tensor:
    """[N, 2D]: each particle's distance to the lower and then the upper bound of every dimension [D, 2], over
    R, clipped to [-1, 1] (App. B.2) or to [-wall_range, wall_range] (`model.wall_range`)."""
    to_lower = (position - bounds[:, 0]) / radius
    to_upper = (bounds[:, 1] - position) / radius
    return torch.clamp(torch.cat([to_lower, to_upper], dim=1), -wall_range, wall_range)


def node_features(window: torch.Tensor, norm: Normalisation, *, bounds: torch.Tensor, radius: float,
                  walls: bool = True, absolute_positions: bool = False,
                  context: torch.Tensor | None = None, wall_range: float = 1.0) -> torch.Tensor:
    """Per-particle input features (the type embedding is appended by the network).

    - the C velocities, normalised by (vel_mean, vel_std'), flattened (Sec. 3.2, encoder input);
    - with walls (`bounds` [D, 2] are walls): distance to the lower and to the upper bound of every
      dimension, divided by R and clipped to [-1, 1] (App. B.2), or to [-wall_range, wall_range];
    - for the absolute-position ablation (Sec. 5.4): the position itself, scaled to [0, 1] over the
      bounds (translation invariance is lost on purpose);
    - the global context, already normalised, per particle [N, C] (e.g. CONTINUOUS' friction angle).
    """
    n = window.shape[0]
    vel = (velocities(window) - norm.vel_mean) / norm.vel_std
    parts = [vel.reshape(n, -1)]
    position = window[:, -1]
    if walls:
        parts.append(wall_distances(position, bounds, radius, wall_range))
    if absolute_positions:
        parts.append((position - bounds[:, 0]) / (bounds[:, 1] - bounds[:, 0]))
    if context is not None:
        parts.append(context)
    return torch.cat(parts, dim=1)


def edge_features(position: torch.Tensor, edge_index: torch.Tensor, radius: float, *,
                  bounds: torch.Tensor, absolute_positions: bool = False) -> torch.Tensor:
    """Per-edge input features.

    Relative encoding (the paper's): (p_sender - p_receiver) / R and its norm (Sec. 3.2, App. B.2).
    Absolute encoding (ablation): the sender's and receiver's positions scaled over the bounds.
    """
    senders = position.index_select(0, edge_index[0])
    receivers = position.index_select(0, edge_index[1])
    if absolute_positions:
        span = bounds[:, 1] - bounds[:, 0]
        return torch.cat([(senders - bounds[:, 0]) / span, (receivers - bounds[:, 0]) / span], dim=1)
    displacement = (senders - receivers) / radius
    return torch.cat([displacement, displacement.norm(dim=1, keepdim=True)], dim=1)


def normalise_context(context: torch.Tensor, norm: Normalisation) -> torch.Tensor:
    return (context - norm.context_mean) / norm.context_std


def integrate(window: torch.Tensor, acceleration: torch.Tensor) -> torch.Tensor:
    """Semi-implicit Euler with dt = 1 (paper Sec. 3.1 and 4.2): v' = v + a; p' = p + v'."""
    last_position = window[:, -1]
    last_velocity = last_position - window[:, -2]
    return last_position + last_velocity + acceleration


def acceleration_from_next_position(window: torch.Tensor, next_position: torch.Tensor) -> torch.Tensor:
    """The inverse of `integrate`: a = p_{t+1} - 2 p_t + p_{t-1}."""
    return next_position - 2.0 * window[:, -1] + window[:, -2]
