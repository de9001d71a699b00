"""The MPM ground-truth solver: runs a scene with the MLS-MPM kernels and stores one state every `dt`.

`simulate(spec, tier_name, rng)` is the entry point the generator dispatches to for `solver = "mpm"`.
The solver substep follows the CFL condition dt_sub <= cfl * dx / (c + v_max), with c the fastest
elastic wave speed of the domain's materials, so that the stored frames keep the domain's `dt` exactly
(dt = substeps * dt_sub).

The background grid has `grid` cells per unit length and covers [0, ceil(upper bound)] in each dimension:
the unit square (cube) for the paper's domains, [0, 8] x [0, 4] for the 8.0 x 4.0 arena of the inflow
generalisation scene (Sec. 5.3).

Inflow (scenes.py `inflow`): emitted particles are preallocated and inactive (mpm_kernels.INACTIVE) until
their birth frame, when they appear at the nozzle with the stream's velocity. Their stored positions before
birth are a prescribed path (`prebirth_path`), which gives a newborn particle the velocity history the
learned simulator's input window needs.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import taichi as ti

from gns_bench.data.format import KINEMATIC_PARTICLE_TYPE, Trajectory
from gns_bench.physics.inflow import prebirth_path
from gns_bench.physics.mpm_kernels import GOOP, INACTIVE, SAND, WATER, build_kernels
from gns_bench.physics.scenes import MpmScene, build_scene, scene_spec
from gns_bench.physics.spec import DomainSpec
from gns_bench.physics.taichi_runtime import ensure_taichi

MATERIAL_MODELS = {"water": WATER, "sand": SAND, "goop": GOOP}


class SimulationError(RuntimeError):
    """A simulation blew up (NaN, or particles outside the container). Nothing of it is written."""


@dataclass(frozen=True)
class MaterialParams:
    """Scalar parameters of the three material models (a domain uses one value per model)."""

    bulk_modulus: float = 400.0  # water, K
    youngs_modulus: float = 1000.0  # sand and goop
    poisson_ratio: float = 0.3
    friction_angle_deg: float = 40.0  # sand, Drucker-Prager
    # goop, von Mises yield and Bingham viscosity (plastic strain rate = (stress - yield) / viscosity; see
    # mpm_kernels.return_mapping). With the earlier 0.3 / 0.1 goop splashed almost like water on impact
    # (Reynolds number ~ 10) and the yield stress then froze the splash's one-particle-thick sheets into
    # saw-tooth spikes up to yield / (rho g) = 0.03 tall (two cells at grid 64) that sloshed on for seconds.
    yield_stress: float = 0.1
    viscosity: float = 0.3

    @property
    def lame(self) -> tuple[float, float]:
        e, nu = self.youngs_modulus, self.poisson_ratio
        return e / (2 * (1 + nu)), e * nu / ((1 + nu) * (1 - 2 * nu))

    @property
    def alpha(self) -> float:
        """Drucker-Prager cone coefficient from the friction angle (Klar et al. 2016, eq. 25)."""
        s = math.sin(math.radians(self.friction_angle_deg))
        return math.sqrt(2.0 / 3.0) * 2.0 * s / (3.0 - s)

    def wave_speed(self, models: set[int]) -> float:
        """Fastest elastic (P-wave) speed, density 1."""
        mu, lam = self.lame
        speeds = [math.sqrt(self.bulk_modulus)] if WATER in models else []
        if models & {SAND, GOOP}:
            speeds.append(math.sqrt(lam + 2 * mu))
        return max(speeds)


def material_params(spec: DomainSpec) -> tuple[MaterialParams, dict[str, int]]:
    """Merge the spec's `[materials.<name>]` tables into one parameter set; name -> model code."""
    merged: dict[str, Any] = {}
    models = {}
    for name, table in spec.materials.items():
        model = table.get("model", name)
        if model not in MATERIAL_MODELS:
            raise ValueError(f"{spec.path}: key 'materials.{name}.model': unknown model {model!r}; "
                             f"expected one of {sorted(MATERIAL_MODELS)}")
        models[name] = MATERIAL_MODELS[model]
        for key, value in table.items():
            if key == "model":
                continue
            if key not in MaterialParams.__dataclass_fields__:
                raise ValueError(f"{spec.path}: key 'materials.{name}.{key}': unknown parameter; expected "
                                 f"one of {sorted(MaterialParams.__dataclass_fields__)}")
            if key in merged and merged[key] != float(value):
                raise ValueError(f"{spec.path}: key 'materials.{name}.{key}': {value} conflicts with "
                                 f"{merged[key]} set by another material; the solver takes one value")
            merged[key] = float(value)
    return MaterialParams(**merged), models


def grid_nodes(bounds: list[list[float]], grid: int) -> tuple[int, ...]:
    """Grid nodes per dimension: `grid` cells per unit length over [0, ceil(upper bound)]."""
    if any(lo < 0.0 for lo, _ in bounds):
        raise ValueError(f"MPM bounds {bounds} must lie in the positive quadrant: the grid starts at 0")
    return tuple(grid * max(1, math.ceil(hi)) + 1 for _, hi in bounds)


class MpmRunner:
    """Holds the particle and grid arrays of one simulation and advances it frame by frame."""

    def __init__(self, scene: MpmScene, params: MaterialParams, *, grid: int, bounds: list[list[float]],
                 gravity: list[float], frame_dt: float, cfl: float, max_speed: float, wall_friction: float):
        ensure_taichi()
        self.scene, self.params = scene, params
        self.dim = dim = scene.position.shape[1]
        self.inv_dx = float(grid)
        dx = 1.0 / grid
        c = params.wave_speed(set(np.unique(scene.material).tolist()))
        self.substeps = max(1, math.ceil(frame_dt / (cfl * dx / (c + max_speed))))
        self.dt = frame_dt / self.substeps
        self.gravity = [float(g) for g in gravity]
        self.wall_friction = wall_friction
        n = scene.position.shape[0]
        vec, mat = ti.types.vector(dim, ti.f32), ti.types.matrix(dim, dim, ti.f32)
        self.x = ti.ndarray(vec, n)
        self.v = ti.ndarray(vec, n)
        self.C = ti.ndarray(mat, n)
        self.F = ti.ndarray(mat, n)
        self.tau = ti.ndarray(mat, n)
        self.material = ti.ndarray(ti.i32, n)
        shape = grid_nodes(bounds, grid)
        self.grid_p = ti.ndarray(ti.types.vector(dim, ti.i64), shape)
        self.grid_m = ti.ndarray(ti.i64, shape)
        self.grid_v = ti.ndarray(vec, shape)
        self.sdf = ti.ndarray(ti.f32, shape)
        self.normal = ti.ndarray(vec, shape)
        self.x.from_numpy(scene.position.astype(np.float32))
        self.v.from_numpy(scene.velocity.astype(np.float32))
        self.C.from_numpy(np.zeros((n, dim, dim), np.float32))
        self.F.from_numpy(np.broadcast_to(np.eye(dim, dtype=np.float32), (n, dim, dim)).copy())
        self.tau.from_numpy(np.zeros((n, dim, dim), np.float32))
        self.material.from_numpy(np.where(scene.birth_step > 0, INACTIVE, scene.material).astype(np.int32))
        sdf, normal = scene.obstacle_sdf(grid, shape)
        self.sdf.from_numpy(sdf.astype(np.float32))
        self.normal.from_numpy(normal.astype(np.float32))
        self.kernel = build_kernels(dim)
        self.time = 0.0

    def advance(self, frame_dt: float) -> None:
        p = self.params
        mu, lam = p.lame
        yield_strain = p.yield_stress / (2 * mu)
        # Bingham relaxation: the deviatoric excess decays at rate 2 mu / viscosity (implicit Euler)
        relax = 1.0 - 1.0 / (1.0 + self.dt * 2 * mu / p.viscosity)
        for _ in range(self.substeps):
            lo, hi, vel = self.scene.container(self.time)
            self.kernel(self.x, self.v, self.C, self.F, self.tau, self.material, self.grid_p, self.grid_m,
                        self.grid_v, self.sdf, self.normal, self.dt, self.inv_dx, self.gravity, lo, hi, vel,
                        p.bulk_modulus, mu, lam, p.alpha, yield_strain, relax, self.wall_friction)
            self.time += self.dt

    def positions(self) -> np.ndarray:
        return self.x.to_numpy()

    def emit(self, born: np.ndarray) -> None:
        """Give the inflow particles `born` (indices) their material: from now on they move. Their position
        and velocity are the scene's (the nozzle row and the stream's velocity); C = 0, F = I and tau = 0
        are still their initial values, as an inactive particle is never updated."""
        for array, values in ((self.x, self.scene.position), (self.v, self.scene.velocity),
                              (self.material, self.scene.material)):
            host = array.to_numpy()
            host[born] = values[born]
            array.from_numpy(host)


def run_scene(scene: MpmScene, params: MaterialParams, *, grid: int, gravity: list[float], frame_dt: float,
              frames: int, bounds: list[list[float]], cfl: float = 0.4, max_speed: float = 5.0,
              wall_friction: float = 0.0, label: str = "mpm") -> np.ndarray:
    """Simulate `frames` stored frames after the initial one; returns material positions [frames+1, N, D].

    An inflow particle sits at its birth position until it is born (`prebirth_path` then rewrites those
    frames). Raises SimulationError as soon as a frame holds NaN or a particle outside `bounds` (by more than
    half a grid cell, the reach of the wall boundary condition).
    """
    runner = MpmRunner(scene, params, grid=grid, bounds=bounds, gravity=gravity, frame_dt=frame_dt, cfl=cfl,
                       max_speed=max_speed, wall_friction=wall_friction)
    births = {int(b): np.flatnonzero(scene.birth_step == b) for b in np.unique(scene.birth_step) if b > 0}
    lo, hi = np.asarray(bounds)[:, 0], np.asarray(bounds)[:, 1]
    tol = 0.5 / grid
    out = np.empty((frames + 1, *scene.position.shape), np.float32)
    out[0] = scene.position
    for t in range(1, frames + 1):
        runner.advance(frame_dt)
        if t in births:
            runner.emit(births[t])
        pos = runner.positions()
        if not np.all(np.isfinite(pos)):
            raise SimulationError(f"{label}: NaN in particle positions at stored frame {t}")
        outside = np.any((pos < lo - tol) | (pos > hi + tol), axis=1)
        if outside.any():
            k = int(np.argmax(outside))
            raise SimulationError(f"{label}: particle {k} left the container at stored frame {t} "
                                  f"(position {pos[k].tolist()}, bounds {np.asarray(bounds).tolist()})")
        out[t] = pos
    return out


@dataclass(frozen=True)
class MpmSettings:
    """The `[mpm]` table and the tier's `grid`, validated: no solver default hides deeper down."""

    grid: int  # cells per unit length (tier key `grid`): across the unit square/cube
    cfl: float  # solver substep = cfl * dx / (wave speed + max_speed)
    max_speed: float  # particle speed the substep must resolve, on top of the wave speed
    wall_friction: float  # Coulomb friction coefficient of walls and obstacles

    @classmethod
    def from_spec(cls, spec: DomainSpec, tier_name: str) -> MpmSettings:
        table = dict(spec.solver_params)
        names = ("cfl", "max_speed", "wall_friction")
        unknown = sorted(set(table) - set(names))
        missing = [k for k in names if k not in table]
        if unknown or missing:
            key = (unknown or missing)[0]
            raise ValueError(f"{spec.path}: key 'mpm.{key}': {'unknown' if unknown else 'missing'}; "
                             f"[mpm] takes exactly {list(names)}")
        tier_params = spec.tier(tier_name).params
        extra = sorted(set(tier_params) - {"grid", "max_particles", "scene", "bounds"})
        if extra:
            raise ValueError(f"{spec.path}: key 'tiers.{tier_name}.{extra[0]}': unknown; an MPM tier takes "
                             "grid, max_particles, scene and bounds besides the trajectory counts")
        grid = tier_params.get("grid")
        if not (isinstance(grid, int) and grid >= 8):
            raise ValueError(f"{spec.path}: key 'tiers.{tier_name}.grid': expected an integer >= 8, "
                             f"got {grid!r}")
        return cls(grid, *(float(table[k]) for k in names))


def simulate(spec: DomainSpec, tier_name: str, rng: np.random.Generator) -> Trajectory:
    """One trajectory of an MPM domain at the given tier, its randomness drawn from `rng`."""
    spec = spec.for_tier(tier_name)
    tier = spec.tier(tier_name)
    params, models = material_params(spec)
    context = None
    if spec.context is not None:
        if spec.context.name != "friction_angle":
            raise ValueError(f"{spec.path}: key 'context.name': the MPM solver understands only "
                             f"'friction_angle' (of its sand), not {spec.context.name!r}")
        context = spec.context.sample(rng)
        params = dataclasses.replace(params, friction_angle_deg=context)
    settings = MpmSettings.from_spec(spec, tier_name)
    scene = build_scene(spec, tier, models, rng)
    frames = tier.sequence_length
    material_pos = run_scene(scene, params, grid=settings.grid, gravity=spec.gravity, frame_dt=spec.dt,
                             frames=frames, bounds=spec.bounds, cfl=settings.cfl, max_speed=settings.max_speed,
                             wall_friction=settings.wall_friction, label=f"{spec.id}/{tier_name}")
    birth_step = None
    if np.any(scene.birth_step > 0):
        prebirth_path(material_pos, scene.birth_step, scene.velocity, spec.dt)
    kinematic = scene.kinematic_positions(spec.dt, frames)  # [T, K, D]
    position = np.concatenate([material_pos, kinematic], axis=1).astype(np.float32)
    types = np.concatenate([scene.particle_type,
                            np.full(kinematic.shape[1], KINEMATIC_PARTICLE_TYPE)]).astype(np.int64)
    if scene_spec(spec, tier).inflow:  # kinematic particles are there from the start
        birth_step = np.concatenate([scene.birth_step, np.zeros(kinematic.shape[1], np.int64)])
    step_context = None
    if context is not None:
        step_context = np.full((frames + 1, 1), context, np.float32)
    return Trajectory(position, types, step_context, birth_step)
