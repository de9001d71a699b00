"""Ground-truth 3D water for WATER-3D and WATER-3D-S: divergence-free SPH (DFSPH) on Taichi.

The paper's 3D water came from SPlisHSPlasH, whose default pressure solver is DFSPH; we implement that
method (Bender & Koschier 2015, 2017), which keeps both the density and the velocity divergence at
their rest values, so a resting pool is still and time steps follow the flow speed, not a sound speed.

  - Kernel: cubic spline W of support h = 2 dx (Monaghan 1992), dx the initial particle spacing.
  - Density (Akinci et al. 2012, eq. 6): rho_i = sum_j m W_ij + sum_b Psi_b W_ib over fluid neighbours j
    and static boundary particles b. Walls are two layers of boundary particles continuing the fluid
    lattice behind each face (`sph_scene.box_boundary_particles`); on that regular sampling Akinci's
    boundary volume Psi_b = rho_0 / sum_k W_bk of a full lattice is the fluid mass, Psi_b = m.
  - DFSPH factor (Bender & Koschier 2017, eq. 11, written as kappa_i / rho_i):
        D_i = |sum_j m grad W_ij + sum_b Psi_b grad W_ib|^2 + sum_j |m grad W_ij|^2.
  - Density solve (their Alg. 2): predicted rho*_i = rho_i + dt [sum_j m v_ij . grad W_ij + sum_b Psi_b
    v_i . grad W_ib]; k_i = max(rho*_i - rho_0, 0) / (dt^2 D_i); then
        v_i -= dt [sum_j m (k_i + k_j) grad W_ij + sum_b Psi_b k_i grad W_ib],
    repeated until the mean relative density error is below `density_tolerance`.
  - Divergence solve (their Alg. 3): the same with k_i = max(D rho_i / Dt, 0) / (dt D_i), for particles
    with a full neighbourhood only, until the mean relative density change per step is below
    `divergence_tolerance`.
  - Non-pressure forces: gravity and XSPH velocity smoothing (Monaghan 1989) as viscosity, with the
    walls' zero velocity in the sum acting as wall friction.
  - Time step: symplectic Euler with the CFL bound dt <= cfl * dx / v_max (their eq. 13), the stored
    interval split into equal sub-steps; the pressure solves are what make this large step stable.
Walls are also a hard position constraint at the faces of the container: boundary particles alone
hold deep water (a resting column never touches that constraint, which the tests check), but a lone
particle or a film one particle thick has too few fluid neighbours to be held a half spacing off the
wall, sinks into the boundary layer and would cross the face; the constraint puts it back on the face
with no outward velocity. `SPHStats.wall_clamps` counts how often (about 0.2% of particle sub-steps in
a paper-tier WATER-3D trajectory, a few % in thin films).

Determinism: no floating-point atomics (sums run in a fixed neighbour order, see `sph_grid`, and the
solvers' error means are serial sums), so a seed gives the same bits on any number of threads.
"""

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import taichi as ti

from gns_bench.data.format import Trajectory
from gns_bench.physics.sph_grid import (
    CellList,
    Grid,
    SimulationError,
    cell_coord,
    cell_index,
    check_frame,
    in_grid,
    ivec3,
    nd_f32,
    nd_i32,
    nd_vec3,
    to_vec3_ndarray,
    vec3,
)
from gns_bench.physics.sph_scene import box_boundary_particles, lattice_mass_factor, sample_water_scene
from gns_bench.physics.taichi_runtime import ensure_taichi

WATER_TYPE = 5
MAX_ITERATIONS = 100
FULL_NEIGHBOURHOOD = 20  # fluid + boundary neighbours below which the divergence solve skips a particle
MAX_NEIGHBOURS = 96  # list capacity: about three times the neighbours at rest density; exceeding it raises
nd_nbr = ti.types.ndarray(dtype=ti.i32, ndim=2)
nd_w = ti.types.ndarray(dtype=ti.f32, ndim=2)
nd_grad = ti.types.ndarray(dtype=vec3, ndim=2)


@dataclass(frozen=True)
class SPHParams:
    """Everything the solver needs; `params_from_spec` builds it from a spec's `[sph]` table."""

    bounds: np.ndarray  # [3, 2] container
    gravity: tuple[float, float, float]
    particle_spacing: float  # dx
    rest_density: float = 1000.0
    xsph: float = 0.05  # XSPH smoothing coefficient (viscosity and wall friction)
    cfl: float = 0.4
    density_tolerance: float = 2e-4  # mean (rho* - rho_0) / rho_0 at which the density solve stops
    divergence_tolerance: float = 1e-3  # mean dt (D rho / Dt) / rho_0 at which the divergence solve stops
    speed_limit: float = 30.0  # m/s; twice the fastest wall jet seen in WATER-3D: the solver blew up

    @property
    def support(self) -> float:
        return 2.0 * self.particle_spacing


@dataclass
class SPHStats:
    substeps: int  # over the whole run
    wall_clamps: int  # particle positions put back on a face by the safety net
    max_speed: float  # over all stored frames, m/s
    max_density_iterations: int
    density: np.ndarray  # [T, N] per-particle density at each stored frame


# ----------------------------------------------------------------------------------------------
# Kernel function (cubic spline, Monaghan 1992) and the neighbour loop
# ----------------------------------------------------------------------------------------------

@ti.func
def kernel_w(r: float, h: float) -> float:
    q = r / h
    k = 8.0 / (math.pi * h * h * h)
    w = 0.0
    if q <= 0.5:
        w = k * (6.0 * q * q * q - 6.0 * q * q + 1.0)
    elif q <= 1.0:
        w = k * 2.0 * (1.0 - q) * (1.0 - q) * (1.0 - q)
    return w


@ti.func
def kernel_grad(d: vec3, h: float) -> vec3:
    r = d.norm()
    q = r / h
    lk = 48.0 / (math.pi * h * h * h)
    g = vec3(0.0)
    if 1e-9 < r and q <= 1.0:
        dwdq = lk * q * (3.0 * q - 2.0) if q <= 0.5 else -lk * (1.0 - q) * (1.0 - q)
        g = dwdq / (h * r) * d
    return g


# Positions stay fixed through a sub-step's two pressure solves, so `_neighbours` walks the 27 cells
# once and caches each pair's W and m grad W; every later pass is a gather over that list. Boundary
# neighbours are stored as -1 (they have zero velocity and no stiffness of their own). A kernel reads a
# neighbour's arrays only under an `if j >= 0:` statement: Taichi evaluates both branches of a conditional
# expression, so `v[j] if j >= 0 else ...` reads v[-1], which segfaulted when the array began a page.

@ti.kernel
def _neighbours(x: nd_vec3, origin: vec3, inv_cell: float, dims: ivec3, start: nd_i32, order: nd_i32,
                xb: nd_vec3, bstart: nd_i32, border: nd_i32, h: float, mass: float,
                nbr: nd_nbr, w: nd_w, grad: nd_grad, count: nd_i32, rho: nd_f32, factor: nd_f32) -> ti.i32:
    """Neighbour lists, density (Akinci eq. 6) and the DFSPH factor 1 / D_i. Returns the largest
    neighbour count; entries past the list's capacity are not stored and the caller raises."""
    cap = nbr.shape[1]
    for i in range(x.shape[0]):
        c0 = cell_coord(x[i], origin, inv_cell, dims)
        nb = 0
        for off in ti.grouped(ti.ndrange((-1, 2), (-1, 2), (-1, 2))):
            c = c0 + off
            if in_grid(c, dims):
                cid = cell_index(c, dims)
                for k in range(start[cid], start[cid + 1]):
                    d = x[i] - x[order[k]]
                    r = d.norm()
                    if r < h:
                        if nb < cap:
                            nbr[i, nb], w[i, nb], grad[i, nb] = order[k], kernel_w(r, h), kernel_grad(d, h)
                        nb += 1
                for k in range(bstart[cid], bstart[cid + 1]):
                    d = x[i] - xb[border[k]]
                    r = d.norm()
                    if r < h:
                        if nb < cap:
                            nbr[i, nb], w[i, nb], grad[i, nb] = -1, kernel_w(r, h), kernel_grad(d, h)
                        nb += 1
        count[i] = nb
        s, grad_sum, grad_sq = 0.0, vec3(0.0), 0.0
        for k in range(ti.min(nb, cap)):
            s += mass * w[i, k]
            g = mass * grad[i, k]
            grad_sum += g
            if nbr[i, k] >= 0:  # boundary particles do not move: no |m grad W|^2 term
                grad_sq += g.dot(g)
        rho[i] = s
        denominator = grad_sum.dot(grad_sum) + grad_sq
        factor[i] = 1.0 / denominator if denominator > 1e-6 * mass * mass / h**8 else 0.0
    largest = 0
    ti.loop_config(serialize=True)
    for i in range(x.shape[0]):
        largest = ti.max(largest, count[i])
    return largest


@ti.kernel
def _solve_stiffness(v: nd_vec3, nbr: nd_nbr, grad: nd_grad, count: nd_i32, mass: float, rho0: float,
                     rho: nd_f32, factor: nd_f32, dt: float, divergence: ti.i32, stiff: nd_f32,
                     err_buf: nd_f32) -> float:
    """Half a solver iteration: k_i from the predicted density (or its rate of change). Returns the
    mean error (relative density excess, or relative density change per step), summed serially."""
    for i in range(v.shape[0]):
        rate = 0.0  # D rho_i / Dt
        for k in range(count[i]):
            j = nbr[i, k]
            vj = vec3(0.0)  # a wall neighbour (j = -1) does not move
            if j >= 0:  # a statement, not `v[j] if j >= 0 else ...`: that would load v[-1] (see below)
                vj = v[j]
            rate += mass * (v[i] - vj).dot(grad[i, k])
        if divergence:
            err = ti.max(rate, 0.0) if count[i] >= FULL_NEIGHBOURHOOD else 0.0
            stiff[i] = err * factor[i] / dt
            err_buf[i] = err * dt / rho0
        else:
            err = ti.max(rho[i] + dt * rate - rho0, 0.0)
            stiff[i] = err * factor[i] / (dt * dt)
            err_buf[i] = err / rho0
    total = 0.0
    ti.loop_config(serialize=True)
    for i in range(v.shape[0]):
        total += err_buf[i]
    return total / v.shape[0]


@ti.kernel
def _apply_stiffness(v: nd_vec3, nbr: nd_nbr, grad: nd_grad, count: nd_i32, mass: float, stiff: nd_f32,
                     dt: float):
    """The other half: v_i -= dt [sum_j m (k_i + k_j) grad W_ij + sum_b Psi_b k_i grad W_ib]."""
    for i in range(v.shape[0]):
        dv = vec3(0.0)
        for k in range(count[i]):
            j = nbr[i, k]
            kj = 0.0
            if j >= 0:
                kj = stiff[j]
            dv -= dt * mass * (stiff[i] + kj) * grad[i, k]
        v[i] += dv


@ti.kernel
def _gravity_xsph(v: nd_vec3, v_new: nd_vec3, nbr: nd_nbr, w: nd_w, count: nd_i32, mass: float, rho0: float,
                  rho: nd_f32, xsph: float, gravity: vec3, dt: float):
    """v_i += dt g + c sum_j (m / rho_j) (v_j - v_i) W_ij, walls counted with v_b = 0, rho_b = rho_0."""
    for i in range(v.shape[0]):
        smooth = vec3(0.0)
        for k in range(count[i]):
            j = nbr[i, k]
            if j >= 0:
                smooth += mass / rho[j] * (v[j] - v[i]) * w[i, k]
            else:
                smooth -= mass / rho0 * v[i] * w[i, k]
        v_new[i] = v[i] + xsph * smooth + dt * gravity
    for i in range(v.shape[0]):
        v[i] = v_new[i]


@ti.kernel
def _move(x: nd_vec3, v: nd_vec3, dt: float, lo: vec3, hi: vec3, clamps: nd_i32):
    for i in range(x.shape[0]):
        xi, vi = x[i] + dt * v[i], v[i]
        for ax in ti.static(range(3)):  # the walls' hard position constraint (module docstring), counted
            if xi[ax] < lo[ax]:
                xi[ax], vi[ax] = lo[ax], ti.max(vi[ax], 0.0)
                ti.atomic_add(clamps[0], 1)
            elif xi[ax] > hi[ax]:
                xi[ax], vi[ax] = hi[ax], ti.min(vi[ax], 0.0)
                ti.atomic_add(clamps[0], 1)
        x[i], v[i] = xi, vi


# ----------------------------------------------------------------------------------------------
# Driver
# ----------------------------------------------------------------------------------------------

class _State:
    """The Taichi arrays of one run and the calls that advance them."""

    def __init__(self, params: SPHParams, position: np.ndarray, velocity: np.ndarray):
        ensure_taichi()
        self.params = params
        bounds = np.asarray(params.bounds, dtype=np.float64)
        dx, n = params.particle_spacing, position.shape[0]
        boundary = box_boundary_particles(bounds, dx)
        self.x, self.v, self.xb = (to_vec3_ndarray(a) for a in (position, velocity, boundary))
        self.v_new = ti.ndarray(vec3, n)
        self.rho, self.factor, self.stiff, self.err = (ti.ndarray(ti.f32, n) for _ in range(4))
        self.count, self.clamps = ti.ndarray(ti.i32, n), ti.ndarray(ti.i32, 1)
        self.nbr = ti.ndarray(ti.i32, (n, MAX_NEIGHBOURS))
        self.w = ti.ndarray(ti.f32, (n, MAX_NEIGHBOURS))
        self.grad = ti.ndarray(vec3, (n, MAX_NEIGHBOURS))
        grid = Grid.covering(bounds, params.support)
        self.cells, wall_cells = CellList(grid, n), CellList(grid, boundary.shape[0])
        wall_cells.build(self.xb)
        self.walls = (self.xb, wall_cells.cell_start, wall_cells.order)
        # Mass such that a perfect lattice of spacing dx sums to rho_0 exactly (no start-up jolt).
        self.mass = params.rest_density * dx**3 * lattice_mass_factor(2.0)
        self.lo, self.hi = vec3(*bounds[:, 0]), vec3(*bounds[:, 1])
        self.max_iterations = 0
        self.update_density()

    def lists(self) -> tuple:
        return (self.nbr, self.grad, self.count, self.mass)

    def update_density(self) -> None:
        self.cells.build(self.x)
        largest = _neighbours(self.x, *self.cells.args(), *self.walls, self.params.support, self.mass,
                              self.nbr, self.w, self.grad, self.count, self.rho, self.factor)
        if largest > MAX_NEIGHBOURS:
            raise SimulationError(f"a particle has {largest} neighbours within the kernel support, more than "
                                  f"the {MAX_NEIGHBOURS} a fluid near rest density can have")

    def solve(self, dt: float, divergence: bool, tolerance: float, min_iterations: int) -> int:
        p = self.params
        for it in range(1, MAX_ITERATIONS + 1):
            error = _solve_stiffness(self.v, *self.lists(), p.rest_density, self.rho, self.factor, dt,
                                     int(divergence), self.stiff, self.err)
            if error <= tolerance and it > min_iterations:
                return it
            _apply_stiffness(self.v, *self.lists(), self.stiff, dt)
        if not error <= 10 * tolerance:
            kind = "divergence" if divergence else "density"
            raise SimulationError(f"DFSPH {kind} solve did not converge: mean error {error:.3g} after "
                                  f"{MAX_ITERATIONS} iterations (tolerance {tolerance:.3g})")
        return MAX_ITERATIONS

    def substep(self, dt: float) -> None:
        p = self.params
        self.solve(dt, True, p.divergence_tolerance, 0)
        _gravity_xsph(self.v, self.v_new, self.nbr, self.w, self.count, self.mass, p.rest_density, self.rho,
                      p.xsph, vec3(*p.gravity), dt)
        iterations = self.solve(dt, False, p.density_tolerance, 1)
        self.max_iterations = max(self.max_iterations, iterations)
        _move(self.x, self.v, dt, self.lo, self.hi, self.clamps)
        self.update_density()


def run_sph(params: SPHParams, position: np.ndarray, velocity: np.ndarray, num_frames: int,
            frame_dt: float, domain: str = "sph") -> tuple[np.ndarray, SPHStats]:
    """Simulate `num_frames` stored intervals from the given state; returns positions [T, N, 3]."""
    state = _State(params, position, velocity)
    bounds = np.asarray(params.bounds, dtype=np.float64)
    tolerance = 0.02 * float(np.max(bounds[:, 1] - bounds[:, 0]))
    g = float(np.linalg.norm(params.gravity))
    frames = np.empty((num_frames + 1, position.shape[0], 3), dtype=np.float32)
    densities = np.empty(frames.shape[:2], dtype=np.float32)
    frames[0], densities[0] = position, state.rho.to_numpy()
    speed = float(np.linalg.norm(velocity, axis=1).max(initial=0.0))
    max_speed, substeps = speed, 0
    for frame in range(1, num_frames + 1):
        # CFL (Bender & Koschier 2017, eq. 13) with the speed gravity can add during the frame.
        nsub = max(1, math.ceil(frame_dt * (speed + g * frame_dt) / (params.cfl * params.particle_spacing)))
        try:
            for _ in range(nsub):
                state.substep(frame_dt / nsub)
        except SimulationError as exc:
            raise SimulationError(f"{domain}: simulation blew up at stored frame {frame}: {exc}") from exc
        substeps += nsub
        frames[frame], densities[frame] = state.x.to_numpy(), state.rho.to_numpy()
        speed = float(np.linalg.norm(state.v.to_numpy(), axis=1).max())
        max_speed = max(max_speed, speed) if np.isfinite(speed) else float("nan")
        check_frame(frames[frame], bounds, tolerance, domain, frame, speed, params.speed_limit)
    stats = SPHStats(substeps, int(state.clamps.to_numpy()[0]), max_speed, state.max_iterations, densities)
    return frames, stats


def params_from_spec(spec: Any) -> SPHParams:
    """The `[sph]` table, the water material's `rest_density`, the container and gravity."""
    known = set(SPHParams.__dataclass_fields__) - {"bounds", "gravity", "rest_density"}
    unknown = sorted(set(spec.solver_params) - known)
    if unknown:
        raise ValueError(f"{spec.path}: key 'sph.{unknown[0]}': unknown; expected some of {sorted(known)}")
    fields = {k: float(v) for k, v in spec.solver_params.items()}
    water = spec.materials.get("water", {})
    if "rest_density" in water:
        fields["rest_density"] = float(water["rest_density"])
    return SPHParams(bounds=np.asarray(spec.bounds, dtype=np.float64), gravity=tuple(spec.gravity), **fields)


def simulate(spec: Any, tier_name: str, rng: np.random.Generator) -> Trajectory:
    """One random WATER-3D(-S) trajectory: water blocks falling and splashing in the container."""
    params = params_from_spec(spec)
    tier = spec.tier(tier_name)
    scene = {**spec.scene, **tier.params.get("scene", {})}
    position, velocity = sample_water_scene(rng, scene, tier.params, params.particle_spacing, params.bounds,
                                            spec.gravity)
    frames, _ = run_sph(params, position, velocity, tier.sequence_length, spec.dt, domain=spec.id)
    return Trajectory(frames, np.full(frames.shape[1], WATER_TYPE, dtype=np.int64))
