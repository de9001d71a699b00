"""Random-walk noise on the input velocities (paper Sec. 4.3, App. B.3; as in DeepMind's released
code, learning_to_simulate/noise_utils.py).

Each of the C = W-1 input velocities gets an independent N(0, (sigma/sqrt(C))^2) increment; the
increments are summed over time (a random walk), so the last velocity carries noise std sigma. The
noisy positions are rebuilt by integrating the noisy velocities from the first position, which gets
no noise, so p~_t - p~_{t-1} = v~_t holds exactly.
"""

from __future__ import annotations

import torch


def random_walk_position_noise(window_shape: tuple[int, int, int], noise_std: float,
                               generator: torch.Generator | None = None,
                               mask: torch.Tensor | None = None,
                               device: torch.device | str = "cpu") -> torch.Tensor:
    """Noise [N, W, D] to add to an input window of W positions; rows where mask is False get none."""
    n, w, d = window_shape
    num_velocities = w - 1
    step_std = noise_std / num_velocities**0.5
    increments = torch.randn((n, num_velocities, d), generator=generator) * step_std
    velocity_noise = torch.cumsum(increments, dim=1)
    position_noise = torch.cat([torch.zeros((n, 1, d)), torch.cumsum(velocity_noise, dim=1)], dim=1)
    position_noise = position_noise.to(device)
    if mask is not None:
        position_noise = position_noise * mask.to(position_noise.dtype)[:, None, None]
    return position_noise


def noisy_training_pair(window: torch.Tensor, next_position: torch.Tensor, position_noise: torch.Tensor,
                        position_correction: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Corrupt an input window with `position_noise` [N, W, D] and shift its target accordingly
    (paper Sec. 4.3, App. C.2). Returns (noisy window, target next position).

    With `position_correction` alpha the target is p_{t+1} + (1 - alpha) n_t, n_t being the noise on the
    last input position: alpha = 0 (the paper's default) asks the model to undo the velocity noise only,
    so the corrected velocity equals the true next velocity; alpha = 1 asks it to also undo the position
    noise, landing on the clean p_{t+1}.
    """
    target = next_position + (1.0 - position_correction) * position_noise[:, -1]
    return window + position_noise, target
