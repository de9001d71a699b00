"""Initial conditions and container sampling for the SPH water domains (and the PBD bath).

A scene is a few axis-aligned blocks of water on the lattice of spacing dx (so blocks never overlap:
their union is taken), optionally a pool covering the floor, each block with its own random velocity,
falling under gravity. The `[scene]` table of a spec sets the ranges; the tier sets the particle budget.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def _cubic_spline(r: np.ndarray, h: float) -> np.ndarray:
    q = r / h
    k = 8.0 / (np.pi * h**3)
    return np.where(q <= 0.5, k * (6 * q**3 - 6 * q**2 + 1), np.where(q <= 1.0, k * 2 * (1 - q) ** 3, 0.0))


def lattice_mass_factor(support_factor: float) -> float:
    """1 / (dx^3 sum_j W(x_i - x_j)) over a simple cubic lattice of unit spacing: scales the particle
    mass rho_0 dx^3 so that a particle inside a perfect lattice has exactly the rest density."""
    reach = int(np.ceil(support_factor))
    k = np.arange(-reach, reach + 1)
    offsets = np.stack(np.meshgrid(k, k, k, indexing="ij"), -1).reshape(-1, 3)
    return float(1.0 / _cubic_spline(np.linalg.norm(offsets, axis=1), support_factor).sum())


def box_boundary_particles(bounds: np.ndarray, dx: float, layers: int = 2) -> np.ndarray:
    """`layers` layers of static boundary particles wrapped around the box `bounds` ([3, 2]), continuing
    the fluid lattice of spacing dx (`fluid_lattice`) outwards through every face, edge and corner.

    Two layers give a particle touching a face a full kernel support (h = 2 dx) of fluid-like
    neighbours, so on this regular sampling Akinci et al.'s boundary volume rho_0 / sum_k W_bk of a
    full lattice is just the fluid particle's: `sph.py` gives boundary particles the fluid mass.
    """
    bounds = np.asarray(bounds, dtype=np.float64)
    shell = dx * (np.arange(layers) + 0.5)
    axes = [np.concatenate([bounds[d, 0] - shell[::-1], inner, bounds[d, 1] + shell])
            for d, inner in enumerate(fluid_lattice(bounds, dx))]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    outside = np.any((points < bounds[:, 0]) | (points > bounds[:, 1]), axis=1)
    return points[outside].astype(np.float32)


def fluid_lattice(bounds: np.ndarray, dx: float) -> list[np.ndarray]:
    """Per-axis lattice coordinates inside `bounds`, dx/2 away from every face."""
    bounds = np.asarray(bounds, dtype=np.float64)
    return [bounds[d, 0] + dx / 2 + dx * np.arange(int(np.floor((bounds[d, 1] - bounds[d, 0]) / dx + 1e-6)))
            for d in range(bounds.shape[0])]


def up_axis(gravity: np.ndarray | list[float]) -> int:
    return int(np.argmax(np.abs(np.asarray(gravity, dtype=float))))


def _range(table: dict[str, Any], key: str, default: list[float]) -> tuple[float, float]:
    lo, hi = table.get(key, default)
    return float(lo), float(hi)


def sample_water_scene(rng: np.random.Generator, scene: dict[str, Any], tier_params: dict[str, Any],
                       dx: float, bounds: np.ndarray, gravity: list[float] | None = None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Random water blocks (and maybe a floor pool) on the dx lattice: positions and velocities [N, 3].

    Scene keys: `num_blocks` [min, max], `pool_probability`, `block_aspect` [min, max] (edge ratio),
    `initial_speed` (max of each velocity component, m/s), `drop_height` [min, max] (the lowest face
    of a falling block, as a fraction of the container height). Tier keys: `min_particles`,
    `max_particles` (the particle budget, drawn uniformly).
    """
    bounds = np.asarray(bounds, dtype=np.float64)
    up = up_axis(gravity if gravity is not None else [0.0, -1.0, 0.0])
    span = bounds[:, 1] - bounds[:, 0]
    budget = int(rng.integers(int(tier_params["min_particles"]), int(tier_params["max_particles"]) + 1))
    nb_lo, nb_hi = (int(v) for v in scene.get("num_blocks", [1, 3]))
    num_blocks = int(rng.integers(nb_lo, nb_hi + 1))
    pool = bool(rng.random() < float(scene.get("pool_probability", 0.0)))
    shares = rng.dirichlet(np.ones(num_blocks + pool))
    aspect_lo, aspect_hi = _range(scene, "block_aspect", [0.5, 2.0])
    drop_lo, drop_hi = _range(scene, "drop_height", [0.2, 0.7])
    speed = float(scene.get("initial_speed", 0.0))

    axes = fluid_lattice(bounds, dx)
    points = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    taken = np.zeros(len(points), dtype=bool)
    velocity = np.zeros_like(points)
    boxes = []
    if pool:
        floor = np.prod(np.delete(span, up))
        depth = min(shares[0] * budget * dx**3 / floor, 0.4 * span[up])
        box = bounds.copy()
        box[up, 1] = bounds[up, 0] + depth
        boxes.append((box, np.zeros(3)))
    for share in shares[int(pool):]:
        aspect = np.exp(rng.uniform(np.log(aspect_lo), np.log(aspect_hi), 3))
        edges = (share * budget * dx**3 / np.prod(aspect)) ** (1 / 3) * aspect
        edges = np.clip(edges, 2 * dx, 0.8 * span)
        corner = bounds[:, 0] + rng.uniform(0.0, 1.0, 3) * (span - edges)
        drop = rng.uniform(drop_lo, drop_hi) * span[up]
        corner[up] = bounds[up, 0] + min(drop, span[up] - edges[up])
        box = np.stack([corner, corner + edges], axis=1)
        boxes.append((box, rng.uniform(-speed, speed, 3)))
    for box, vel in boxes:
        inside = np.all((points >= box[:, 0]) & (points < box[:, 1]), axis=1) & ~taken
        velocity[inside] = vel
        taken |= inside
    if taken.sum() > int(tier_params["max_particles"]):  # lattice rounding overshot the budget: redraw
        smaller = int(0.95 * budget)
        budget_params = {"min_particles": min(int(tier_params["min_particles"]), smaller),
                         "max_particles": smaller}
        return sample_water_scene(rng, scene, budget_params, dx, bounds, gravity)
    if not taken.any():  # a block thinner than one lattice cell: take the nearest lattice point
        taken[np.argmin(np.linalg.norm(points - boxes[-1][0].mean(axis=1), axis=1))] = True
    return points[taken].astype(np.float32), velocity[taken].astype(np.float32)
