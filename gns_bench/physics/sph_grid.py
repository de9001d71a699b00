"""Deterministic uniform-grid neighbour search and checks shared by the SPH and PBD solvers (Taichi).

Particles are bucketed into cubic cells no smaller than the kernel support by a counting sort whose
scatter pass runs serially, so the particles of a cell are always listed in index order and every
neighbour sum is accumulated in the same order whatever the number of threads. No kernel of either
solver uses a floating-point atomic, so a trajectory is bitwise reproducible from its seed.

Arrays are Taichi ndarrays (not fields) so each kernel compiles once for every particle count.
"""


from dataclasses import dataclass

import numpy as np
import taichi as ti

# One error type for every ground-truth solver: the MPM module's, re-exported here for SPH and PBD.
from gns_bench.physics.mpm import SimulationError

__all__ = ["CellList", "Grid", "SimulationError", "check_frame", "to_vec3_ndarray"]

vec3 = ti.math.vec3
ivec3 = ti.math.ivec3
# Kernel argument types of the SPH and PBD solvers: 1D ndarrays of vectors, floats and indices.
nd_vec3 = ti.types.ndarray(dtype=vec3, ndim=1)
nd_f32 = ti.types.ndarray(dtype=ti.f32, ndim=1)
nd_i32 = ti.types.ndarray(dtype=ti.i32, ndim=1)


@dataclass(frozen=True)
class Grid:
    """A uniform grid of cubic cells covering `bounds` plus one cell of margin on every side."""

    origin: tuple[float, float, float]
    cell_size: float
    dims: tuple[int, int, int]

    @classmethod
    def covering(cls, bounds: np.ndarray, cell_size: float) -> "Grid":
        bounds = np.asarray(bounds, dtype=np.float64)
        dims = np.ceil((bounds[:, 1] - bounds[:, 0]) / cell_size).astype(int) + 2
        origin = bounds[:, 0] - cell_size
        return cls(tuple(float(o) for o in origin), float(cell_size), tuple(int(d) for d in dims))

    @property
    def num_cells(self) -> int:
        return self.dims[0] * self.dims[1] * self.dims[2]

    def args(self) -> tuple:
        """The grid as the (origin, inverse cell size, dims) kernel arguments."""
        return vec3(*self.origin), 1.0 / self.cell_size, ivec3(*self.dims)


class CellList:
    """The sorted particle order and per-cell ranges of one particle set on one grid."""

    def __init__(self, grid: Grid, num_particles: int):
        self.grid = grid
        self.cell_start = ti.ndarray(ti.i32, grid.num_cells + 1)
        self.cell_fill = ti.ndarray(ti.i32, grid.num_cells)
        self.order = ti.ndarray(ti.i32, max(num_particles, 1))
        self.cell_of = ti.ndarray(ti.i32, max(num_particles, 1))

    def build(self, x: ti.Ndarray) -> None:
        origin, inv_cell, dims = self.grid.args()
        _build(x, origin, inv_cell, dims, self.cell_start, self.cell_fill, self.order, self.cell_of)

    def args(self) -> tuple:
        """(origin, inverse cell size, dims, cell_start, order) for the neighbour loops."""
        return (*self.grid.args(), self.cell_start, self.order)


@ti.func
def cell_coord(p: vec3, origin: vec3, inv_cell: float, dims: ivec3) -> ivec3:
    c = ti.floor((p - origin) * inv_cell, ti.i32)
    return ti.math.clamp(c, 0, dims - 1)


@ti.func
def cell_index(c: ivec3, dims: ivec3) -> ti.i32:
    return (c[0] * dims[1] + c[1]) * dims[2] + c[2]


@ti.func
def in_grid(c: ivec3, dims: ivec3) -> bool:
    return 0 <= c[0] < dims[0] and 0 <= c[1] < dims[1] and 0 <= c[2] < dims[2]


@ti.kernel
def _build(x: ti.types.ndarray(dtype=vec3, ndim=1), origin: vec3, inv_cell: float, dims: ivec3,
           cell_start: ti.types.ndarray(dtype=ti.i32, ndim=1), cell_fill: ti.types.ndarray(dtype=ti.i32, ndim=1),
           order: ti.types.ndarray(dtype=ti.i32, ndim=1), cell_of: ti.types.ndarray(dtype=ti.i32, ndim=1)):
    n = x.shape[0]
    num_cells = cell_fill.shape[0]
    for c in range(num_cells):
        cell_fill[c] = 0
    for i in range(n):
        cell_of[i] = cell_index(cell_coord(x[i], origin, inv_cell, dims), dims)
    ti.loop_config(serialize=True)
    for i in range(n):
        cell_fill[cell_of[i]] += 1
    ti.loop_config(serialize=True)
    for c in range(num_cells + 1):
        if c == 0:
            cell_start[0] = 0
        else:
            cell_start[c] = cell_start[c - 1] + cell_fill[c - 1]
    for c in range(num_cells):
        cell_fill[c] = 0
    # The scatter runs serially so particles of a cell keep their index order (determinism).
    ti.loop_config(serialize=True)
    for i in range(n):
        c = cell_of[i]
        order[cell_start[c] + cell_fill[c]] = i
        cell_fill[c] += 1


def to_vec3_ndarray(array: np.ndarray) -> ti.Ndarray:
    out = ti.ndarray(vec3, array.shape[0])
    out.from_numpy(np.ascontiguousarray(array, dtype=np.float32))
    return out


def check_frame(position: np.ndarray, bounds: np.ndarray, tolerance: float, domain: str, frame: int,
                max_speed: float | None = None, speed_limit: float | None = None) -> None:
    """Raise `SimulationError` naming the domain and the stored frame if the state is garbage."""
    if not np.all(np.isfinite(position)):
        bad = int(np.argwhere(~np.isfinite(position))[0][0])
        raise SimulationError(f"{domain}: simulation blew up at stored frame {frame}: NaN or inf position "
                              f"(first particle {bad})")
    lo, hi = position.min(axis=0), position.max(axis=0)
    if np.any(lo < bounds[:, 0] - tolerance) or np.any(hi > bounds[:, 1] + tolerance):
        raise SimulationError(f"{domain}: simulation blew up at stored frame {frame}: particles span "
                              f"[{lo.tolist()}, {hi.tolist()}], outside the container {bounds.tolist()}")
    if max_speed is not None and speed_limit is not None and not max_speed <= speed_limit:
        raise SimulationError(f"{domain}: simulation blew up at stored frame {frame}: a particle moves at "
                              f"{max_speed:.3g} m/s, above the solver's stability limit {speed_limit:.3g} m/s")
