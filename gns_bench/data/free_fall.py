"""Free fall in a trajectory, and the held-still windows made from it.

Where the ground truth is in free fall its answer is known without a solver: every particle accelerates at g.
The physical diagnostics ask a model for g there (`evaluate/diagnostics.py`), and training can show it a
state its windows never hold: the same material at rest in mid-air, let go (`held_still`). Every window of a
trajectory carries the motion before it, so a block at rest in mid-air appears in training only where a scene
releases one from rest, and then only after its first frames have set it falling; yet it is the state a
rollout reaches when it stops a block in mid-air, and a model that has never been shown it may keep it there
(a block that hovers). A stress-free body let go from rest falls at g in its first step, so the held window's
target is known exactly where every moving particle of the frame is in free fall.

Accelerations are second differences of positions per stored frame (dt = 1, as the metadata's statistics).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gns_bench.data.format import KINEMATIC_PARTICLE_TYPE, Trajectory

FREE_FALL_TOLERANCE = 0.1  # |a - g| <= 0.1 |g|: MPM particles in a falling block jitter a little about g
FREE_FALL_RUN = 3  # frames in a row: a particle passing through g for one frame of an impact is not falling


def accelerations(frames: np.ndarray) -> np.ndarray:
    """[T, N, D] positions -> [T - 2, N, D] accelerations a_t = p_{t+1} - 2 p_t + p_{t-1} (t = 1 .. T-2)."""
    frames = np.asarray(frames, dtype=np.float64)
    return frames[2:] - 2.0 * frames[1:-1] + frames[:-2]


def free_fall_mask(acceleration: np.ndarray, gravity: Sequence[float],
                   tolerance: float = FREE_FALL_TOLERANCE, run: int = FREE_FALL_RUN) -> np.ndarray:
    """[T, N] True where a particle's acceleration [T, N, D] is g within `tolerance` |g| on `run` consecutive
    frames centred on that one (frames too near either end to have their neighbours count as False)."""
    g = np.asarray(gravity, dtype=np.float64)
    close = np.linalg.norm(acceleration - g, axis=-1) <= tolerance * np.linalg.norm(g)
    half = run // 2
    mask = np.zeros_like(close)
    if close.shape[0] < run:
        return mask
    inner = np.ones_like(close[: close.shape[0] - 2 * half])
    for shift in range(run):
        inner &= close[shift: shift + inner.shape[0]]
    mask[half: half + inner.shape[0]] = inner
    return mask


def falling_frames(trajectory: Trajectory, gravity: Sequence[float]) -> np.ndarray:
    """The frames at which every moving particle of `trajectory` is in free fall in it (`free_fall_mask`);
    none for a trajectory with inflow (its particles are not all present) or no moving particle."""
    moving = trajectory.particle_type != KINEMATIC_PARTICLE_TYPE
    if trajectory.has_inflow or not moving.any() or trajectory.num_steps < 3:
        return np.zeros(0, dtype=np.int64)
    falling = free_fall_mask(accelerations(trajectory.position), gravity)[:, moving].all(axis=1)
    return np.flatnonzero(falling) + 1  # acceleration index i is frame i + 1


def held_still(trajectory: Trajectory, frame: int, window: int, future: int, gravity: Sequence[float],
               released: int = 0) -> Trajectory:
    """A trajectory of `window + released + future` frames: the material of `frame` held still for `window`
    frames, then let go: its moving particles fall at g from rest, p_k = p + g k(k+1)/2 after k steps of the
    model's integration (v' = v + a, p' = p + v'), its kinematic ones stay. Its window to train on ends
    `released` steps after the release, at frame `window - 1 + released`: with `released` 0 every input
    velocity is 0; up to `window - 1` the window holds the rest and the first steps of the fall, the windows a
    rollout passes through after it stopped a block in mid-air. Exact for a frame of `falling_frames` (a body
    in free fall is free of stress)."""
    frames = window + released + future
    held = np.repeat(trajectory.position[frame: frame + 1].astype(np.float64), frames, axis=0)
    moving = trajectory.particle_type != KINEMATIC_PARTICLE_TYPE
    steps = np.arange(1, frames - window + 1, dtype=np.float64)
    fall = (steps * (steps + 1) / 2)[:, None] * np.asarray(gravity, dtype=np.float64)[None, :]
    held[window:, moving] += fall[:, None, :]
    context = (None if trajectory.step_context is None
               else np.repeat(trajectory.step_context[frame: frame + 1], frames, axis=0))
    return Trajectory(held.astype(trajectory.position.dtype), trajectory.particle_type, context)
