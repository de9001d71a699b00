"""Inflow emitters of the MPM scenes: streams of material entering through nozzles (2D).

The paper's generalisation scene (Knowl 7) has "multiple streams pouring continuously into an arena" of
8.0 x 4.0. A stream is a nozzle, a segment of width `width` centred on `position` and perpendicular to the
stream's `velocity`, that emits one row of particles at the lattice spacing s every s / |v| seconds from
stored frame `start` until frame `stop`: a continuous stream at the density of the scenes' blocks.

Particles are preallocated: the scene holds every particle the run will emit, each with its birth frame.
Row k of a stream leaves the nozzle at t_k = start dt + k s / |v|; it is born at the first stored frame
b_k = ceil(t_k / dt) at or after that, already advanced by v (b_k dt - t_k), so that rows stay s apart
although births fall on frame boundaries. Before b_k the solver skips it (mpm_kernels.INACTIVE).

Stored positions before birth (`prebirth_path`): the straight path p_b + v (t - b) dt for the
HISTORY_FRAMES frames t in [b - 6, b), and p_{b-6} for every earlier frame. A particle born at b thus
has a velocity history for the learned simulator's input window (C = 5 velocities, 6 positions, Knowl 1)
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

    def row_offsets(self, spacing: float) -> np.ndarray:
        """[M, 2] positions of one row relative to the nozzle centre: M = round(width / s) particles s
        apart across the stream."""
        across = np.array([-self.velocity[1], self.velocity[0]]) / self.speed
        count = max(1, round(self.width / spacing))
        return (np.arange(count) - (count - 1) / 2)[:, None] * spacing * across

    def particles(self, spacing: float, dt: float, frames: int) -> tuple[np.ndarray, np.ndarray]:
        """Birth positions [P, 2] and birth frames [P] of every particle emitted up to stored frame
        `frames`, in order of birth."""
        row_frames = spacing / (self.speed * dt)  # frames between rows
        last = min(self.stop, frames)
        k = np.arange(math.floor((last - self.start) / row_frames) + 2)
        leave = self.start + k * row_frames  # when row k leaves the nozzle, in frames
        birth = np.ceil(leave - 1e-9).astype(np.int64)
        keep = birth <= last
        leave, birth = leave[keep], birth[keep]
        centres = self.position + ((birth - leave) * dt)[:, None] * self.velocity  # advanced since leaving
        offsets = self.row_offsets(spacing)
        pos = (centres[:, None, :] + offsets[None]).reshape(-1, 2)
        return pos, np.repeat(birth, len(offsets))

    def reach(self, spacing: float, dt: float) -> np.ndarray:
        """[4, 2] corners of the region a row covers from HISTORY_FRAMES frames before its birth to its
        birth (the stored pre-birth path and the nozzle)."""
        ends = self.row_offsets(spacing)[[0, -1]]
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
