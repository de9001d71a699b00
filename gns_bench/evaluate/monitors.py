"""Rollout health monitors: hooks that stop a rollout the moment it produces garbage, or flag it.

Each monitor looks at the newly predicted positions and raises `MonitorTripped` (a `RolloutStopped`)
naming itself, the step, the value it saw and its threshold; the rollout keeps the state where it
tripped. The paper's failure modes this catches: NaN/inf, particles escaping the container, kinetic
energy blowing up, and particles collapsing onto each other. `arm` wraps the monitors that should not end
a rollout in `Flag`, which records the first trip and lets the rollout run on.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from gns_bench.evaluate.metrics import kinetic_energy
from gns_bench.evaluate.rollout import RolloutState, RolloutStopped


class MonitorTripped(RolloutStopped):
    def __init__(self, monitor: str, step: int, value: float, threshold: float, detail: str,
                 position: np.ndarray):
        super().__init__(f"{monitor} at step {step}: {detail}")
        self.monitor, self.step, self.value, self.threshold = monitor, step, value, threshold
        self.position = position


def _step_energy(position: torch.Tensor, previous: torch.Tensor, moving: torch.Tensor) -> float:
    """Kinetic energy of one step (metrics.kinetic_energy, on the moving particles)."""
    return float(kinetic_energy(position.detach().cpu().numpy()[None], previous.detach().cpu().numpy(),
                                moving.cpu().numpy())[0])


@dataclass
class FiniteMonitor:
    """Trips on any NaN or inf position."""

    name: str = "non_finite"

    def __call__(self, state: RolloutState) -> None:
        finite = torch.isfinite(state.position).all(dim=1)
        if not bool(finite.all()):
            bad = int((~finite).sum())
            raise MonitorTripped(self.name, state.step, float(bad), 0.0, f"{bad} particles with NaN or inf",
                                 state.position.cpu().numpy())


@dataclass
class BoundsMonitor:
    """Trips when a particle leaves the bounds by more than `margin` (a length, e.g. a few R)."""

    bounds: np.ndarray  # [D, 2]
    margin: float
    name: str = "out_of_bounds"

    def __call__(self, state: RolloutState) -> None:
        p = state.position.detach().cpu().numpy()
        bounds = np.asarray(self.bounds)
        excess = np.maximum(bounds[:, 0] - p, p - bounds[:, 1]).max()
        if excess > self.margin:
            raise MonitorTripped(self.name, state.step, float(excess), self.margin,
                                 f"a particle is {excess:.3g} outside the bounds (margin {self.margin:.3g})", p)


@dataclass
class EnergyMonitor:
    """Trips when the moving particles' kinetic energy exceeds `factor` x the larger of the initial
    state's, the ground truth's at that step (when given) and a floor (motion of R/10 a step), so a
    scene at rest cannot trip it on noise."""

    moving: torch.Tensor  # [N] bool
    initial_energy: float
    radius: float
    factor: float = 10.0
    reference: np.ndarray | None = None  # [K] ground-truth kinetic energy per rollout step
    name: str = "energy_blowup"

    def __call__(self, state: RolloutState) -> None:
        energy = _step_energy(state.position, state.window[:, -1], self.moving)
        reference = max(self.initial_energy, 0.5 * (self.radius / 10) ** 2)
        if self.reference is not None and state.step < len(self.reference):
            reference = max(reference, float(self.reference[state.step]))
        if not energy <= self.factor * reference:  # also trips on NaN energy
            raise MonitorTripped(self.name, state.step, energy, self.factor * reference,
                                 f"kinetic energy {energy:.3g} > {self.factor:g} x reference {reference:.3g}",
                                 state.position.cpu().numpy())


def close_share(position: np.ndarray, moving: np.ndarray, cutoff: float) -> float:
    """The share of the moving particles with another particle closer than `cutoff` (positions [N, D])."""
    distance, _ = cKDTree(position).query(position[moving], k=2)
    return float(np.mean(distance[:, 1] < cutoff))


@dataclass
class DensityMonitor:
    """Trips when more than `max_share` of the moving particles have a neighbour closer than
    `fraction` x R (local density collapse); checked every `every` steps to stay cheap. With the ground
    truth's positions (`reference`, [K, N, D] per rollout step), a trip also says the truth's share at
    that step, so a reader sees the stop is the model's and not the data's: the solvers' own scenes peak at
    2.0-7.5% (2D MPM) and at most 0.7% (3D, PBD) over the test splits of every cpu-tier dataset, while a
    WATERDROP model run on past its trip reached 26% by step 100 and 75% by step 550, with 8x the truth's
    pairs within R (reports/NOTES.md). It also needs at least `min_close` particles that close: a share of a
    handful is noise, not a collapse (the inflow arena's first frames hold 7 moving particles, 2 of them as
    close in the truth as in the model: 28.6%)."""

    moving: torch.Tensor
    radius: float
    fraction: float = 0.05
    max_share: float = 0.1
    every: int = 10
    reference: np.ndarray | None = None
    min_close: int = 10
    name: str = "density_collapse"

    def __call__(self, state: RolloutState) -> None:
        if state.step % self.every:
            return
        p = state.position.detach().cpu().numpy().astype(np.float64)
        if not np.all(np.isfinite(p)):
            return  # FiniteMonitor's business
        moving = self.moving.cpu().numpy()
        present = None if state.present is None else state.present.cpu().numpy()
        if present is not None:  # inflow: particles waiting to enter are not in the scene yet
            p, moving = p[present], moving[present]
        if not moving.any():
            return
        share = close_share(p, moving, self.fraction * self.radius)
        if share > self.max_share and round(share * moving.sum()) >= self.min_close:
            detail = f"{share:.1%} of particles within {self.fraction:g} R of another"
            if self.reference is not None and state.step < len(self.reference):
                truth = self.reference[state.step].astype(np.float64)
                truth = truth if present is None else truth[present]
                detail += f" (the ground truth: {close_share(truth, moving, self.fraction * self.radius):.1%})"
            raise MonitorTripped(self.name, state.step, share, self.max_share, detail, p)


def default_monitors(bounds: Sequence[Sequence[float]], radius: float, initial_window: torch.Tensor,
                     moving: torch.Tensor, reference_energy: np.ndarray | None = None,
                     reference_position: np.ndarray | None = None) -> list:
    """The monitors every rollout runs: finite, within bounds (margin 3 R), energy (10x), density; the
    ground truth per rollout step (kinetic energy [K], positions [K, N, D]) where known."""
    initial = _step_energy(initial_window[:, -1], initial_window[:, -2], moving)
    return [FiniteMonitor(), BoundsMonitor(np.asarray(bounds, dtype=np.float64), 3 * radius),
            EnergyMonitor(moving, initial, radius, reference=reference_energy),
            DensityMonitor(moving, radius, reference=reference_position)]


@dataclass
class Flag:
    """Runs `monitor` until it first trips, keeps that trip in `tripped`, and never stops the rollout."""

    monitor: Callable[[RolloutState], None]
    tripped: MonitorTripped | None = None

    def __call__(self, state: RolloutState) -> None:
        if self.tripped is None:
            try:
                self.monitor(state)
            except MonitorTripped as trip:
                self.tripped = trip


def arm(monitors: Sequence, stop_on: Sequence[str]) -> list:
    """The monitors named in `stop_on` as they are (they end a rollout), every other one wrapped in `Flag`."""
    return [m if m.name in stop_on else Flag(m) for m in monitors]


def flags(hooks: Sequence) -> list[MonitorTripped]:
    """The trips that the `Flag` hooks among `hooks` recorded, in rollout order."""
    return sorted((h.tripped for h in hooks if isinstance(h, Flag) and h.tripped is not None),
                  key=lambda trip: trip.step)
