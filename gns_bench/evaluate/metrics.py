"""Error metrics as pure functions (paper Sec. 4.4, REFERENCE.md 'Evaluation').

Position MSE is the squared coordinate error averaged over steps, particles and dimensions; kinematic
particles (which follow the data) are excluded through `mask` (True = counted).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

DEFAULT_HORIZONS = (1, 10, 100)


def position_mse(predicted: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean squared position error over [..., N, D]; mask [N] selects the particles that count."""
    if predicted.shape != truth.shape:
        raise ValueError(f"shape mismatch: predicted {predicted.shape} vs truth {truth.shape}")
    error = np.square(predicted.astype(np.float64) - truth.astype(np.float64))
    if mask is not None:
        if not mask.any():
            raise ValueError("no particle selected by the mask")
        error = error[..., mask, :]
    return float(error.mean())


def rollout_mse(predicted: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Full-rollout MSE: mean over every predicted step [K, N, D] (the paper's rollout metric)."""
    return position_mse(predicted, truth, mask)


def mse_at_horizons(predicted: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None,
                    horizons: Sequence[int] = DEFAULT_HORIZONS) -> dict[int, float]:
    """MSE averaged over the first h rollout steps, for each horizon h the rollout reaches."""
    return {h: position_mse(predicted[:h], truth[:h], mask) for h in horizons if h <= predicted.shape[0]}


def constant_velocity_rollout(initial_window: np.ndarray, num_steps: int) -> np.ndarray:
    """Baseline: every particle keeps its last velocity. initial_window [W, N, D] -> [K, N, D]."""
    last, velocity = initial_window[-1], initial_window[-1] - initial_window[-2]
    steps = np.arange(1, num_steps + 1, dtype=np.float64)[:, None, None]
    return (last[None] + steps * velocity[None]).astype(initial_window.dtype)
