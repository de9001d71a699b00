"""A rollout's outcome as plain arrays: what evaluation scores, reports draw and npz files hold. NumPy only,
so readers of runs (reports) need neither torch nor the model."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gns_bench.data.format import KINEMATIC_PARTICLE_TYPE


class RolloutStopped(Exception):
    """Raised by a hook to end a rollout early; the rollout records the step and the reason."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


@dataclass
class RolloutResult:
    predicted: np.ndarray  # [K, N, D] predicted frames W .. W+K-1 (fewer if stopped)
    ground_truth: np.ndarray  # [K', N, D] the true frames over the requested horizon
    initial_window: np.ndarray  # [W, N, D]
    particle_type: np.ndarray  # [N]
    stopped_at: int | None = None
    stop_reason: str | None = None
    stopped_by: RolloutStopped | None = None  # the exception a hook raised (a monitor carries its details)
    birth_step: np.ndarray | None = None  # [N] inflow: the frame each particle enters (None: all from the start)

    @property
    def moving_mask(self) -> np.ndarray:
        return self.particle_type != KINEMATIC_PARTICLE_TYPE

    def shown_at(self, step: int) -> np.ndarray:
        """[N] the particles that exist at predicted frame `step` (inflow particles from their birth frame on);
        pictures draw these."""
        if self.birth_step is None:
            return np.ones(len(self.particle_type), bool)
        return self.birth_step <= self.initial_window.shape[0] + step

    def scored_mask(self, num_steps: int | None = None) -> np.ndarray:
        """The particles whose error counts: [N] moving particles, or [K, N] moving particles present at
        each predicted frame when particles enter over time (inflow)."""
        moving = self.moving_mask
        if self.birth_step is None:
            return moving
        k = self.predicted.shape[0] if num_steps is None else num_steps
        w = self.initial_window.shape[0]
        frames = np.arange(w, w + k)[:, None]
        return moving[None] & (self.birth_step[None] <= frames - 1)


# What a stress test returns (gns_bench/stress): plain data (no model, no torch), so the stability report and the
# figures read results back from a run's `stress/<test>.json` without loading a simulator or the experiments.
@dataclass
class StressResult:
    name: str
    metrics: dict[str, float] = field(default_factory=dict)
    curves: dict[str, list[float]] = field(default_factory=dict)  # per rollout step, NaN where not reached
    trips: list[str] = field(default_factory=list)  # "<scene> trajectory i: <monitor> at step k: ..."
    notes: list[str] = field(default_factory=list)
