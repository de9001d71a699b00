"""One-step training samples: windows of W+1 consecutive frames, batched as disjoint graphs.

A sample is (trajectory index, t): input positions t-W+1 .. t and the target t+1 (as in
DeepMind's released code, learning_to_simulate/train.py). Batches are drawn from a generator seeded by
(seed, step), so any step's batch can be rebuilt without replaying the ones before it: resuming a run is exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from gns_bench.data.format import Trajectory
from gns_bench.data.free_fall import held_still


@dataclass
class GraphBatch:
    """Disjoint graphs concatenated along the particle axis."""

    window: torch.Tensor  # [sum N, W, D] input positions
    particle_type: torch.Tensor  # [sum N]
    batch: torch.Tensor  # [sum N] graph index
    context: torch.Tensor | None  # [B, C] context at the last input frame
    target: torch.Tensor | None  # [sum N, D] next positions (None when there is no target frame)
    future: torch.Tensor | None = None  # [sum N, S, D] the S frames after the window (unrolled training)

    @property
    def num_graphs(self) -> int:
        return int(self.batch[-1]) + 1

    def to(self, device: torch.device | str) -> GraphBatch:
        def move(t: torch.Tensor | None) -> torch.Tensor | None:
            return None if t is None else t.to(device, non_blocking=True)

        return GraphBatch(move(self.window), move(self.particle_type), move(self.batch), move(self.context),
                          move(self.target), move(self.future))


def make_batch(trajectories: list[Trajectory], samples: list[tuple[int, int]], window: int,
               with_target: bool = True, future: int = 1) -> GraphBatch:
    """Stack samples (trajectory index, last input frame t) into one batch of disjoint graphs; with `future`
    > 1, the S = future frames after each window too (architectures trained on unrolled steps)."""
    windows, types, graph, contexts, targets, futures = [], [], [], [], [], []
    for index, (traj_index, t) in enumerate(samples):
        traj = trajectories[traj_index]
        frames = traj.position[t - window + 1: t + 1]  # [W, N, D]
        windows.append(np.swapaxes(frames, 0, 1))
        types.append(traj.particle_type)
        graph.append(np.full(traj.num_particles, index, dtype=np.int64))
        if traj.step_context is not None:
            contexts.append(traj.step_context[t])
        if with_target:
            targets.append(traj.position[t + 1])
        if future > 1:
            futures.append(np.swapaxes(traj.position[t + 1: t + 1 + future], 0, 1))
    return GraphBatch(
        window=torch.from_numpy(np.concatenate(windows)),
        particle_type=torch.from_numpy(np.concatenate(types)),
        batch=torch.from_numpy(np.concatenate(graph)),
        context=torch.from_numpy(np.stack(contexts)) if contexts else None,
        target=torch.from_numpy(np.concatenate(targets)) if with_target else None,
        future=torch.from_numpy(np.concatenate(futures)) if futures else None,
    )


class WindowSampler:
    """Random training windows over all trajectories, deterministic per (seed, step): uniform over every
    window, as the release draws them, or with a share `start_share` of each batch drawn from the first
    `start_windows` windows of a trajectory chosen uniformly.

    Rollouts start from a trajectory's first frames (Sec. 4.4), where blocks are in the air and nearly at rest:
    the only frames where that state occurs, and about 1% of the uniform draws of a 1000-frame trajectory. A
    resting block looks the same to its interior particles (the wall distance is clipped at R, App. B.2), so
    a model that has seen the start rarely resolves "at rest" as "on the floor" and the block hovers.
    `start_share` shows it the start more often (tests/learning: a share of 0 hovers where 0.25 falls).

    With `held_share`, that share of each batch (drawn after the rest) is replaced by held-still windows
    (`data/free_fall.held_still`): a frame where every moving particle is in free fall, chosen uniformly among
    `held_frames` (per trajectory), held at rest and let go, the window ending 0 to `window - 1` steps (drawn
    uniformly) after the release, its target the fall from rest at `gravity`.
    `draw` returns the trajectories its samples index, these windows appended."""

    def __init__(self, trajectories: list[Trajectory], window: int, seed: int, future: int = 1,
                 start_share: float = 0.0, start_windows: int = 50, held_share: float = 0.0,
                 held_frames: list[np.ndarray] | None = None, gravity: list[float] | None = None):
        self.trajectories = trajectories
        self.window = window
        self.seed = seed
        self.future = future  # frames after the window each sample needs (1: the one-step target)
        if not 0.0 <= start_share <= 1.0:
            raise ValueError(f"start_share must be in [0, 1], got {start_share}")
        self.start_share, self.start_windows = start_share, start_windows
        if not 0.0 <= held_share <= 1.0:
            raise ValueError(f"held_share must be in [0, 1], got {held_share}")
        self.held_share, self.gravity = held_share, gravity
        self._held = (np.concatenate([np.stack([np.full(len(f), i), f], axis=1) for i, f in enumerate(held_frames)])
                      if held_share > 0 and held_frames else np.zeros((0, 2), dtype=np.int64))  # (trajectory, frame)
        if held_share > 0 and (gravity is None or not len(self._held)):
            raise ValueError("held-still windows need gravity and a frame where every moving particle is in free "
                             "fall" + ("" if gravity is None else ": no training trajectory has one"))
        # Valid last-input frames t: window-1 .. T-1-future (t+future must exist).
        self.counts = np.array([traj.num_steps - window - future + 1 for traj in trajectories], dtype=np.int64)
        if np.any(self.counts < 1):
            short = int(np.argmin(self.counts))
            raise ValueError(f"trajectory {short} has {trajectories[short].num_steps} frames; a training "
                             f"window needs {window + future}")
        self.offsets = np.concatenate([[0], np.cumsum(self.counts)])

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def rng(self, step: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, step])

    def samples(self, step: int, batch_size: int) -> list[tuple[int, int]]:
        rng = self.rng(step)
        flat = rng.integers(0, len(self), size=batch_size)
        traj = np.searchsorted(self.offsets, flat, side="right") - 1
        index = flat - self.offsets[traj]  # the window's index within its trajectory
        if self.start_share > 0:  # drawn after the uniform draw, so a share of 0 leaves every batch as it was
            early = rng.random(batch_size) < self.start_share
            start_traj = rng.integers(0, len(self.trajectories), size=batch_size)
            start_index = rng.integers(0, np.iinfo(np.int64).max, size=batch_size) % np.minimum(
                self.counts[start_traj], self.start_windows)
            traj = np.where(early, start_traj, traj)
            index = np.where(early, start_index, index)
        t = index + self.window - 1
        return [(int(i), int(j)) for i, j in zip(traj, t, strict=True)]

    def draw(self, step: int, batch_size: int) -> tuple[list[Trajectory], list[tuple[int, int]]]:
        """`samples`, with a share `held_share` of them replaced by held-still windows: (the trajectories the
        samples index, the samples). Without held windows, the training trajectories themselves."""
        samples = self.samples(step, batch_size)
        if self.held_share == 0:
            return self.trajectories, samples
        rng = np.random.default_rng([self.seed, step, 2])  # its own stream: the other draws stay as they were
        held = np.flatnonzero(rng.random(batch_size) < self.held_share)
        picks = self._held[rng.integers(0, len(self._held), size=len(held))]
        released = rng.integers(0, self.window, size=len(held))  # 0: at rest; up to the window: falling from it
        trajectories = list(self.trajectories)
        for slot, (traj, frame), steps in zip(held, picks, released, strict=True):
            trajectories.append(held_still(self.trajectories[traj], int(frame), self.window, self.future,
                                           self.gravity, int(steps)))
            samples[slot] = (len(trajectories) - 1, self.window - 1 + int(steps))
        return trajectories, samples

    def batch(self, step: int, batch_size: int) -> GraphBatch:
        trajectories, samples = self.draw(step, batch_size)
        return make_batch(trajectories, samples, self.window, future=self.future)

    def noise_generator(self, step: int) -> torch.Generator:
        generator = torch.Generator()
        generator.manual_seed(int(np.random.default_rng([self.seed, step, 1]).integers(0, 2**62)))
        return generator
