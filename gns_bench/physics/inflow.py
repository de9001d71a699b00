"""Inflow emitters of the MPM scenes: streams of material entering through nozzles (2D).

The paper's generalisation scene (Sec. 5.3) has "multiple streams pouring continuously into an arena" of
8.0 x 4.0. A stream is a nozzle, a segment of width `width` centred on `position` and perpendicular to the
stream's `velocity`, that emits M = round(width / s) particles every s / |v| seconds (s: the scenes'
spacing) from stored frame `start` until frame `stop`: a continuous stream at the density of the scenes'
blocks, one particle per s^2.

Particles are seeded at random, as the blocks are (geometry.random_block): the k-th batch of M fills the
slab of stream that crosses the nozzle in [t_k, t_k + s / |v|), t_k = start dt + k s / |v|, each particle
at a uniform place across the nozzle's M cells (width M s) and leaving it at a uniform time in that
interval, i.e. i.i.d. uniform in the slab: no rows on a lattice, a regularity the blocks no longer have.

Particles are preallocated: the scene holds every particle the run will emit, each with its birth frame.
A particle leaving the nozzle at time t is born at the first stored frame b = ceil(t / dt) at or after
that, already advanced by v (b dt - t), so that the stream keeps its density although births fall on
frame boundaries. Before b the solver skips it (mpm_kernels.INACTIVE).

Stored positions before birth (`prebirth_path`): the straight path p_b + v (t - b) dt for the
HISTORY_FRAMES frames t in [b - 6, b), and p_{b-6} for every earlier frame. A particle born at b thus
has a velocity history for the learned simulator's input window (C = 5 velocities, 6 positions, Sec. 4.2)
and sits still before; the data's `birth_step` says from which frame it is real. The path reaches
6 |v| dt behind the nozzle, which must lie inside the container (`Emitter.check_inside`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

HISTORY_FRAMES = 6  # positions in the learned simulator's input window: C = 5 velocities
EMITTER_KEYS = ("position", "velocity", "width", "start", "stop", "material")


@dataclass(frozen=True)
class Emitter:
    """One nozzle of a scene's `inflow` list."""

    position: np.ndarray  # [2] centre of the nozzle
    velocity: np.ndarray  # [2] velocity of the stream (units per second)
    width: float  # nozzle width, across the velocity
    start: int  # first stored frame at which it emits
    stop: int  # it emits no row born after this frame
    material: str  # a particle_types name with a [materials] entry

    @property
    def speed(self) -> float:
        return float(np.linalg.norm(self.velocity))

    @property
    def across(self) -> np.ndarray:
        """Unit vector across the stream (along the nozzle)."""
        return np.array([-self.velocity[1], self.velocity[0]]) / self.speed

    def row_count(self, spacing: float) -> int:
        """M = round(width / s): particles emitted per s / |v| seconds, the nozzle's cells s wide."""
        return max(1, round(self.width / spacing))

    def row_offsets(self, spacing: float) -> np.ndarray:
        """[M, 2] centres of the nozzle's M cells relative to its centre, s apart across the stream."""
        count = self.row_count(spacing)
        return (np.arange(count) - (count - 1) / 2)[:, None] * spacing * self.across

    def particles(self, spacing: float, dt: float, frames: int,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Birth positions [P, 2] and birth frames [P] of every particle emitted up to stored frame
        `frames`, in order of birth; each batch of M i.i.d. uniform in its slab of stream (module doc)."""
        row_frames = spacing / (self.speed * dt)  # frames between batches
        last = min(self.stop, frames)
        count = self.row_count(spacing)
        k = np.arange(math.floor((last - self.start) / row_frames) + 2)
        # when each particle leaves the nozzle, in frames, and where across it
        leave = (self.start + (k[:, None] + rng.random((len(k), count))) * row_frames).ravel()
        offset = ((rng.random((len(k), count)) - 0.5) * (count * spacing)).ravel()
        birth = np.ceil(leave - 1e-9).astype(np.int64)
        keep = birth <= last
        leave, birth, offset = leave[keep], birth[keep], offset[keep]
        pos = (self.position + ((birth - leave) * dt)[:, None] * self.velocity  # advanced since leaving
               + offset[:, None] * self.across)
        order = np.argsort(birth, kind="stable")
        return pos[order], birth[order]

    def reach(self, spacing: float, dt: float) -> np.ndarray:
        """[4, 2] corners of the region a particle covers from HISTORY_FRAMES frames before its birth to its
        birth (the stored pre-birth path and the nozzle's M cells)."""
        ends = np.array([-0.5, 0.5])[:, None] * (self.row_count(spacing) * spacing) * self.across
        back, ahead = -HISTORY_FRAMES * dt * self.velocity, dt * self.velocity
        return np.array([self.position + e + d for e in ends for d in (back, ahead)])

    def check_inside(self, lo: np.ndarray, hi: np.ndarray, margin: float, spacing: float, dt: float,
                     where: str) -> None:
        """Raise ValueError (prefixed with `where`, the file and key) unless `reach` lies in the container."""
        corners = self.reach(spacing, dt)
        if np.any(corners < lo + margin) or np.any(corners > hi - margin):
            raise ValueError(f"{where}: the nozzle and its particles' pre-birth path (6 frames back along "
                             f"the velocity) span {corners.min(axis=0).tolist()} to "
                             f"{corners.max(axis=0).tolist()}, not inside the container {lo.tolist()} to "
                             f"{hi.tolist()} by {margin:.4g}; move the nozzle inwards")


def parse_emitters(table: Any, path: str, key: str, materials: dict[str, Any], dim: int) -> list[Emitter]:
    """The `inflow` scene key (`key` in the spec file `path`): a list of tables with exactly EMITTER_KEYS."""

    def fail(name: str, problem: str) -> ValueError:
        return ValueError(f"{path}: key '{key}{name}': {problem}")

    if dim != 2:
        raise fail("", "inflow is implemented for 2D scenes only")
    if not isinstance(table, list):
        raise fail("", f"expected a list of tables {{ {', '.join(EMITTER_KEYS)} }}")
    emitters = []
    for i, e in enumerate(table):
        if not isinstance(e, dict) or set(e) != set(EMITTER_KEYS):
            got = sorted(e) if isinstance(e, dict) else e
            raise fail(f"[{i}]", f"expected a table with exactly the keys {list(EMITTER_KEYS)}, got {got}")
        vectors = {}
        for name in ("position", "velocity"):
            v = e[name]
            if not (isinstance(v, list) and len(v) == 2 and all(isinstance(c, int | float) for c in v)):
                raise fail(f"[{i}].{name}", f"expected 2 numbers, got {v!r}")
            vectors[name] = np.asarray(v, float)
        if not np.linalg.norm(vectors["velocity"]) > 0:
            raise fail(f"[{i}].velocity", "a stream needs a non-zero velocity")
        if isinstance(e["width"], bool) or not (isinstance(e["width"], int | float) and e["width"] > 0):
            raise fail(f"[{i}].width", f"expected a positive length, got {e['width']!r}")
        start, stop = e["start"], e["stop"]
        if not (isinstance(start, int) and isinstance(stop, int) and 0 <= start < stop):
            raise fail(f"[{i}].stop", f"expected stored frames 0 <= start < stop, got {start!r}, {stop!r}")
        if e["material"] not in materials:
            raise fail(f"[{i}].material", f"{e['material']!r} is not a material of this spec "
                       f"({sorted(materials)})")
        emitters.append(Emitter(vectors["position"], vectors["velocity"], float(e["width"]), start, stop,
                                e["material"]))
    return emitters


def prebirth_path(position: np.ndarray, birth: np.ndarray, velocity: np.ndarray, dt: float) -> None:
    """Overwrite, in place, the stored frames before each particle's birth with its prescribed path.

    position [T, N, D] holds each particle's birth position p_b at frame b = birth[i]; velocity [N, D] is
    its stream's. Frames t in [b - 6, b) get p_b + v (t - b) dt, earlier frames p_b - 6 v dt.
    """
    for b in np.unique(birth[birth > 0]):
        idx = np.flatnonzero(birth == b)
        p_b, v = position[b, idx].astype(np.float64), velocity[idx]
        first = max(0, b - HISTORY_FRAMES)
        for t in range(first, b):
            position[t, idx] = p_b + v * ((t - b) * dt)
        if first > 0:
            position[:first, idx] = p_b - v * (HISTORY_FRAMES * dt)
