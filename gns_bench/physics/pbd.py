"""Ground-truth BOXBATH: position-based fluids with a shape-matched rigid cube, on Taichi.

The paper's BOXBATH came from NVIDIA FleX (position-based dynamics): a block of water breaks like a dam
and pushes a rigid cube across a box. We implement the two FleX ingredients it needs.

Position-based fluids (Macklin & Mueller 2013, their Alg. 1), per sub-step:
  - predict x*_i = x_i + dt (v_i + dt g);
  - `iterations` times: for every water particle the density constraint C_i = rho_i / rho_0 - 1 with
    rho_i = sum_j m W_poly6(x*_i - x*_j) over water and cube neighbours (eqs. 1-2), kept unilateral
    (C_i >= 0, as in FleX) and static wall particles continuing the lattice behind each wall counted too;
        lambda_i = -C_i / (sum_k w_k |grad_k C_i|^2 + eps)                         (eqs. 8-11)
        dx_i = w_i (m / rho_0) sum_j (lambda_i + lambda_j + s_corr) grad W_spiky(x*_i - x*_j)  (eq. 12)
    where s_corr = -k (W(r) / W(0.2 h))^4 is their artificial pressure between water particles (eq. 13:
    it keeps spray particles from passing through each other) and w_k the inverse mass relative to
    water (a cube particle of relative density s has w = 1 / s, so the same constraint pushes a light
    cube further: it floats; Macklin et al. 2014, Sec. 5); then particles are projected into the box;
  - the cube is made rigid again by shape matching (Mueller et al. 2005, eqs. 5-7 with stiffness 1):
        c = mean_i x*_i,  A = sum_i (x*_i - c) q_i^T,  R = polar part of A,  x*_i = c + R q_i,
    q_i the rest offsets, after every iteration and last of all, so stored frames hold an exact cube;
  - v_i = (x*_i - x_i) / dt, XSPH viscosity on the water (their eq. 17), x_i = x*_i.
Kernels: poly6 for densities and spiky for gradients (Mueller et al. 2003), support h = 2 dx; rho_0 is
the density of a perfect lattice of spacing dx, so the initial water block starts at rest density.

Shaking (the paper's FLUIDSHAKE-BOX, App. C.7): with scene keys `shake_amplitude` [min, max] (metres)
and `shake_frequency` [min, max] (Hz) the water and the cube sit in a container `container_width` (a
fraction of the bounds' x span) wide, centred, which moves as x_c(t) = A sin(w t) along x; A is clipped
so that it stays inside the bounds. Its walls, floor and lid (the static particles behind each face)
move with it and the box projection follows it, so the moving walls push the water. Its two side walls
are stored as kinematic particles (type 3), one layer on each face, on the fluid lattice.

Determinism: as in `sph.py` (fixed neighbour order, serial sums, no float atomics).
"""

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import taichi as ti

from gns_bench.data.format import Trajectory
from gns_bench.physics.sph_grid import (
    CellList,
    Grid,
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
from gns_bench.physics.sph_scene import box_boundary_particles, fluid_lattice
from gns_bench.physics.taichi_runtime import ensure_taichi

WATER_TYPE = 5
RIGID_TYPE = 0
KINEMATIC_TYPE = 3
nd_mat3 = ti.types.ndarray(dtype=ti.math.mat3, ndim=1)


@dataclass(frozen=True)
class PBDParams:
    """The `[pbd]` table of a spec, plus the container and gravity."""

    bounds: np.ndarray  # [3, 2]
    gravity: tuple[float, float, float]
    particle_spacing: float  # dx
    substeps: int = 2  # per stored frame
    iterations: int = 4  # constraint iterations per sub-step
    relaxation: float = 0.01  # eps as a fraction of sum_k |grad_k C|^2 at rest (constraint softness)
    xsph: float = 0.01
    artificial_pressure: float = 0.01  # Macklin & Mueller's k (n = 4, dq = 0.2 h) as a relative density
    cube_relative_density: float = 0.5
    speed_limit: float = 20.0  # m/s; beyond it the run blew up

    @property
    def support(self) -> float:
        return 2.0 * self.particle_spacing


@ti.func
def poly6(r: float, h: float) -> float:
    w = 0.0
    if r < h:
        w = 315.0 / (64.0 * math.pi * h**9) * (h * h - r * r) ** 3
    return w


@ti.func
def spiky_grad(d: vec3, h: float) -> vec3:
    r = d.norm()
    g = vec3(0.0)
    if 1e-9 < r < h:
        g = -45.0 / (math.pi * h**6) * (h - r) ** 2 / r * d
    return g


@ti.kernel
def _predict(x: nd_vec3, v: nd_vec3, xp: nd_vec3, gravity: vec3, dt: float):
    for i in range(x.shape[0]):
        v[i] += dt * gravity
        xp[i] = x[i] + dt * v[i]


@ti.kernel
def _lambdas(xp: nd_vec3, origin: vec3, inv_cell: float, dims: ivec3, start: nd_i32, order: nd_i32,
             xb: nd_vec3, bstart: nd_i32, border: nd_i32, num_water: ti.i32, inv_mass: nd_f32, h: float,
             volume: float, rho0: float, eps: float, lam: nd_f32):
    """lambda_i of the unilateral density constraint; zero for cube particles (they carry none)."""
    for i in range(xp.shape[0]):
        lam_i = 0.0
        if i < num_water:
            c0 = cell_coord(xp[i], origin, inv_cell, dims)
            rho, grad_i, grad_sq = 0.0, vec3(0.0), 0.0
            for off in ti.grouped(ti.ndrange((-1, 2), (-1, 2), (-1, 2))):
                c = c0 + off
                if in_grid(c, dims):
                    cid = cell_index(c, dims)
                    for k in range(start[cid], start[cid + 1]):
                        j = order[k]
                        d = xp[i] - xp[j]
                        rho += volume * rho0 * poly6(d.norm(), h)
                        g = volume * spiky_grad(d, h)  # = -grad_{x_j} C_i
                        grad_i += g
                        if j != i:
                            grad_sq += inv_mass[j] * g.dot(g)
                    for k in range(bstart[cid], bstart[cid + 1]):  # walls: count, never move
                        d = xp[i] - xb[border[k]]
                        rho += volume * rho0 * poly6(d.norm(), h)
                        grad_i += volume * spiky_grad(d, h)
            constraint = ti.max(rho / rho0 - 1.0, 0.0)
            lam_i = -constraint / (grad_sq + inv_mass[i] * grad_i.dot(grad_i) + eps)
        lam[i] = lam_i


@ti.kernel
def _project(xp: nd_vec3, dxp: nd_vec3, origin: vec3, inv_cell: float, dims: ivec3, start: nd_i32,
             order: nd_i32, xb: nd_vec3, bstart: nd_i32, border: nd_i32, num_water: ti.i32,
             inv_mass: nd_f32, h: float, volume: float, lam: nd_f32, s_corr: float, lo: vec3, hi: vec3):
    """dx_i = w_i V sum_j (lambda_i + lambda_j + s_corr_ij) grad W_ij, then the box projection."""
    w_q = poly6(0.2 * h, h)
    for i in range(xp.shape[0]):
        c0 = cell_coord(xp[i], origin, inv_cell, dims)
        delta = vec3(0.0)
        for off in ti.grouped(ti.ndrange((-1, 2), (-1, 2), (-1, 2))):
            c = c0 + off
            if in_grid(c, dims):
                cid = cell_index(c, dims)
                for k in range(start[cid], start[cid + 1]):
                    j = order[k]
                    d = xp[i] - xp[j]
                    corr = 0.0
                    if i < num_water and j < num_water:  # Macklin & Mueller eq. 13, between water only
                        corr = -s_corr * (poly6(d.norm(), h) / w_q) ** 4
                    delta += (lam[i] + lam[j] + corr) * spiky_grad(d, h)
                for k in range(bstart[cid], bstart[cid + 1]):
                    delta += lam[i] * spiky_grad(xp[i] - xb[border[k]], h)
        dxp[i] = inv_mass[i] * volume * delta
    for i in range(xp.shape[0]):
        xp[i] = ti.math.clamp(xp[i] + dxp[i], lo, hi)


@ti.kernel
def _shape_match(xp: nd_vec3, rest: nd_vec3, num_water: ti.i32, frame: nd_mat3, centre: nd_vec3):
    """Mueller et al. 2005: the best rigid fit of the rest shape, then every cube particle on it."""
    num_rigid = rest.shape[0]
    ti.loop_config(serialize=True)
    for _ in range(1):
        c = vec3(0.0)
        for k in range(num_rigid):
            c += xp[num_water + k]
        c /= num_rigid
        a = ti.math.mat3(0.0)
        for k in range(num_rigid):
            a += (xp[num_water + k] - c).outer_product(rest[k])
        r, _s = ti.polar_decompose(a)
        frame[0], centre[0] = r, c
    for k in range(num_rigid):
        xp[num_water + k] = centre[0] + frame[0] @ rest[k]


@ti.kernel
def _finish(x: nd_vec3, xp: nd_vec3, v: nd_vec3, v_new: nd_vec3, origin: vec3, inv_cell: float, dims: ivec3,
            start: nd_i32, order: nd_i32, num_water: ti.i32, h: float, volume: float, xsph: float, dt: float):
    for i in range(x.shape[0]):
        vi = (xp[i] - x[i]) / dt
        v_new[i] = vi
    for i in range(num_water):  # XSPH on the water only: the cube's velocity is its rigid motion
        c0 = cell_coord(xp[i], origin, inv_cell, dims)
        smooth = vec3(0.0)
        for off in ti.grouped(ti.ndrange((-1, 2), (-1, 2), (-1, 2))):
            c = c0 + off
            if in_grid(c, dims):
                cid = cell_index(c, dims)
                for k in range(start[cid], start[cid + 1]):
                    j = order[k]
                    smooth += (v_new[j] - v_new[i]) * volume * poly6((xp[i] - xp[j]).norm(), h)
        v[i] = v_new[i] + xsph * smooth
    for i in range(num_water, x.shape[0]):
        v[i] = v_new[i]
    for i in range(x.shape[0]):
        x[i] = xp[i]


# ----------------------------------------------------------------------------------------------
# Scene and driver
# ----------------------------------------------------------------------------------------------

def _lattice_sums(dx: float, h: float) -> tuple[float, float]:
    """Particle volume V = 1 / sum_j W_poly6 over a perfect lattice (so it sits at rest density), and
    sum_j |V grad W_spiky|^2 there (the scale of the constraint gradients, for eps)."""
    k = np.arange(-2, 3)
    d = np.stack(np.meshgrid(k, k, k, indexing="ij"), -1).reshape(-1, 3) * dx
    r = np.linalg.norm(d, axis=1)
    inside = r < h
    w = 315.0 / (64.0 * np.pi * h**9) * (h * h - r[inside] ** 2) ** 3
    volume = 1.0 / w.sum()
    ri, di = r[inside & (r > 0)], d[inside & (r > 0)]
    grad = -45.0 / (np.pi * h**6) * ((h - ri) ** 2 / ri)[:, None] * di
    return float(volume), float((volume**2 * (grad**2).sum(axis=1)).sum())


def sample_boxbath_scene(rng: np.random.Generator, scene: dict[str, Any], tier_params: dict[str, Any],
                         dx: float, bounds: np.ndarray) -> tuple[np.ndarray, int, np.ndarray]:
    """A dam of water against one end wall (x) spanning the box's depth (z), and a cube standing on the
    floor (y) in the free part, turned by a random angle about the vertical.

    Returns (positions [N, 3] with the water first, the number of water particles, the cube's rest
    offsets [K, 3]). Scene keys: `dam_height` [min, max] (fraction of the container height), `cube_gap`
    (clearance to the dam, metres), `cube_drop` [min, max] (cube's lift above the floor, metres).
    Tier keys: `water_particles`, `cube_edge` (particles along an edge of the cube).
    """
    bounds = np.asarray(bounds, dtype=np.float64)
    span = bounds[:, 1] - bounds[:, 0]
    cells = np.floor(span / dx + 1e-6).astype(int)
    target = int(tier_params["water_particles"])
    h_lo, h_hi = scene.get("dam_height", [0.4, 0.8])
    ny = int(np.clip(round(rng.uniform(h_lo, h_hi) * cells[1]), 1, cells[1]))
    nx = int(np.clip(round(target / (ny * cells[2])), 1, int(0.6 * cells[0])))
    left = bool(rng.random() < 0.5)
    ix = np.arange(nx) if left else np.arange(cells[0] - nx, cells[0])
    grid = np.stack(np.meshgrid(ix, np.arange(ny), np.arange(cells[2]), indexing="ij"), -1).reshape(-1, 3)
    water = bounds[:, 0] + (grid + 0.5) * dx

    edge = int(tier_params["cube_edge"])
    k = np.arange(edge) - (edge - 1) / 2
    rest = np.stack(np.meshgrid(k, k, k, indexing="ij"), -1).reshape(-1, 3) * dx
    half = 0.5 * edge * dx * math.sqrt(2.0)  # horizontal reach of the turned cube
    gap = float(scene.get("cube_gap", 0.05))
    dam_x = (bounds[0, 0] + nx * dx) if left else (bounds[0, 1] - nx * dx)
    free = (dam_x + gap + half, bounds[0, 1] - half) if left else (bounds[0, 0] + half, dam_x - gap - half)
    if free[0] > free[1]:
        raise ValueError(f"boxbath scene: no room for a {edge}-particle cube beside a dam of {nx} columns")
    drop_lo, drop_hi = scene.get("cube_drop", [0.0, 0.1])
    centre = np.array([rng.uniform(*free),
                       bounds[1, 0] + 0.5 * edge * dx + rng.uniform(drop_lo, drop_hi),
                       rng.uniform(bounds[2, 0] + half, bounds[2, 1] - half)])
    angle = rng.uniform(0.0, 0.5 * math.pi)
    cos, sin = math.cos(angle), math.sin(angle)
    turn = np.array([[cos, 0.0, sin], [0.0, 1.0, 0.0], [-sin, 0.0, cos]])
    cube = centre + rest @ turn.T
    return np.concatenate([water, cube]).astype(np.float32), len(water), rest.astype(np.float32)


@dataclass(frozen=True)
class Shake:
    """A container narrower than the bounds, moving as x_c(t) = amplitude sin(omega t) along x."""

    container: np.ndarray  # [3, 2] the container at rest
    amplitude: float  # metres
    omega: float  # radians per second

    def offset(self, t: float) -> float:
        return self.amplitude * math.sin(self.omega * t)

    def side_walls(self, dx: float) -> np.ndarray:
        """[K, 3] one layer of particles on each side face (x = lo, x = hi) of the container at rest."""
        _, ys, zs = fluid_lattice(self.container, dx)
        yz = np.stack(np.meshgrid(ys, zs, indexing="ij"), -1).reshape(-1, 2)
        faces = [np.column_stack([np.full(len(yz), x), yz]) for x in self.container[0]]
        return np.concatenate(faces).astype(np.float32)


def sample_shake(rng: np.random.Generator, scene: dict[str, Any], bounds: np.ndarray) -> Shake | None:
    """The shaking of one trajectory from the scene keys (None without `shake_amplitude`)."""
    if "shake_amplitude" not in scene:
        return None
    if "shake_frequency" not in scene:
        raise ValueError("pbd scene: shaking needs both shake_amplitude and shake_frequency")
    bounds = np.asarray(bounds, dtype=np.float64)
    amplitude = float(rng.uniform(*scene["shake_amplitude"]))
    omega = 2 * math.pi * float(rng.uniform(*scene["shake_frequency"]))
    span = bounds[0, 1] - bounds[0, 0]
    width = float(scene.get("container_width", 0.7)) * span
    container = bounds.copy()
    container[0] = [bounds[0, 0] + (span - width) / 2, bounds[0, 1] - (span - width) / 2]
    return Shake(container, min(amplitude, (span - width) / 2), omega)


def run_pbd(params: PBDParams, position: np.ndarray, num_water: int, rest: np.ndarray, num_frames: int,
            frame_dt: float, domain: str = "pbd", shake: Shake | None = None) -> np.ndarray:
    """Simulate from rest; the particles after `num_water` are the cube. Returns positions [T, N, 3].

    With `shake` the container (walls, floor, lid) moves along x; otherwise it is the bounds, at rest."""
    ensure_taichi()
    bounds = np.asarray(params.bounds, dtype=np.float64)
    container = bounds if shake is None else shake.container
    dx, h, n = params.particle_spacing, params.support, position.shape[0]
    volume, grad_scale = _lattice_sums(dx, h)
    walls = box_boundary_particles(container, dx)  # static particles continuing the lattice behind the walls
    inv_mass = np.ones(n, dtype=np.float32)
    inv_mass[num_water:] = 1.0 / params.cube_relative_density
    x, v, xp, dxp, v_new = (to_vec3_ndarray(a) for a in (position, np.zeros_like(position), position,
                                                            np.zeros_like(position), np.zeros_like(position)))
    rest_nd = to_vec3_ndarray(rest)
    w, lam = ti.ndarray(ti.f32, n), ti.ndarray(ti.f32, n)
    w.from_numpy(inv_mass)
    frame_mat, centre = ti.ndarray(ti.math.mat3, 1), ti.ndarray(vec3, 1)
    grid = Grid.covering(bounds, h)
    cells, wall_cells = CellList(grid, n), CellList(grid, len(walls))
    xb = to_vec3_ndarray(walls)
    wall_cells.build(xb)
    wall_args = (xb, wall_cells.cell_start, wall_cells.order)
    # Particles are points kept half a spacing from the walls, like the water's initial lattice.
    lo, hi = vec3(*(container[:, 0] + dx / 2)), vec3(*(container[:, 1] - dx / 2))
    dt = frame_dt / params.substeps
    step = 0
    eps = params.relaxation * grad_scale
    s_corr = params.artificial_pressure / grad_scale  # k as a density violation, turned into a lambda
    tolerance = 0.02 * float(np.max(bounds[:, 1] - bounds[:, 0]))
    frames = np.empty((num_frames + 1, n, 3), dtype=np.float32)
    frames[0] = position
    for frame in range(1, num_frames + 1):
        for _ in range(params.substeps):
            step += 1
            if shake is not None:  # the container where it is at the end of this sub-step
                off = np.array([shake.offset(step * dt), 0.0, 0.0])
                xb.from_numpy((walls + off).astype(np.float32))
                wall_cells.build(xb)
                lo, hi = vec3(*(container[:, 0] + off + dx / 2)), vec3(*(container[:, 1] + off - dx / 2))
            _predict(x, v, xp, vec3(*params.gravity), dt)
            cells.build(xp)
            for _ in range(params.iterations):
                _lambdas(xp, *cells.args(), *wall_args, num_water, w, h, volume, 1.0, eps, lam)
                _project(xp, dxp, *cells.args(), *wall_args, num_water, w, h, volume, lam, s_corr, lo, hi)
                _shape_match(xp, rest_nd, num_water, frame_mat, centre)
            _finish(x, xp, v, v_new, *cells.args(), num_water, h, volume, params.xsph, dt)
        frames[frame] = x.to_numpy()
        speed = float(np.linalg.norm(v.to_numpy(), axis=1).max())
        check_frame(frames[frame], bounds, tolerance, domain, frame, speed, params.speed_limit)
    return frames


def params_from_spec(spec: Any) -> PBDParams:
    """The `[pbd]` table, the cube's `materials.rigid.relative_density`, the container and gravity."""
    known = {f.name for f in fields(PBDParams)} - {"bounds", "gravity", "cube_relative_density"}
    unknown = sorted(set(spec.solver_params) - known)
    if unknown:
        raise ValueError(f"{spec.path}: key 'pbd.{unknown[0]}': unknown; expected some of {sorted(known)}")
    kinds = {f.name: f.type for f in fields(PBDParams)}
    values = {k: (int(v) if kinds[k] in (int, "int") else float(v)) for k, v in spec.solver_params.items()}
    rigid = spec.materials.get("rigid", {})
    if "relative_density" in rigid:
        values["cube_relative_density"] = float(rigid["relative_density"])
    return PBDParams(bounds=np.asarray(spec.bounds, dtype=np.float64), gravity=tuple(spec.gravity), **values)


def simulate(spec: Any, tier_name: str, rng: np.random.Generator) -> Trajectory:
    """One random BOXBATH trajectory: a dam of water breaks against a floating rigid cube."""
    params = params_from_spec(spec)
    tier = spec.tier(tier_name)
    scene = {**spec.scene, **tier.params.get("scene", {})}
    shake = sample_shake(rng, scene, params.bounds)
    position, num_water, rest = sample_boxbath_scene(rng, scene, tier.params, params.particle_spacing,
                                                     params.bounds if shake is None else shake.container)
    frames = run_pbd(params, position, num_water, rest, tier.sequence_length, spec.dt, domain=spec.id,
                     shake=shake)
    types = np.full(frames.shape[1], WATER_TYPE, dtype=np.int64)
    types[num_water:] = RIGID_TYPE
    if shake is not None:  # the side walls, as kinematic particles at the container's offset of each frame
        walls = shake.side_walls(params.particle_spacing)
        offsets = np.array([shake.offset(t * spec.dt) for t in range(frames.shape[0])])
        moving = np.repeat(walls[None].astype(np.float64), frames.shape[0], axis=0)
        moving[:, :, 0] += offsets[:, None]
        frames = np.concatenate([frames, moving.astype(np.float32)], axis=1)
        types = np.concatenate([types, np.full(len(walls), KINEMATIC_TYPE, dtype=np.int64)])
    return Trajectory(frames, types)
