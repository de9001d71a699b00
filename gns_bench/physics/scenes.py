"""Initial conditions of the MPM domains, drawn from a spec's `[scene]` table.

Keys of `[scene]` (a tier may override any of them in `[tiers.<name>.scene]`):
  blocks            [min, max]   number of material blocks
  block_size        [min, max]   side length of a block, per dimension
  block_materials   [names]      each block's material is drawn from these (particle_types names)
  initial_speed     max          each block gets a velocity uniform in [-max, max] per dimension
  on_floor          bool         blocks rest on the floor (columns) instead of being placed anywhere
  ramps             [min, max]   number of static ramps: thin rectangles at random angles (2D)
  ramp_length, ramp_angle_deg, ramp_thickness
  random_floor      int          number of piecewise-linear floor segments (0: flat container floor)
  floor_height      [min, max]   heights of the floor's vertices above the container bottom
  shake_amplitude   [min, max]   horizontal shaking of the container (fraction of the bounds)
  shake_frequency   [min, max]   in Hz
  container_width   fraction of the bounds' width taken by the shaken container
Obstacles become static grid boundaries in the solver and kinematic particles (type 3) in the data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gns_bench.physics.spec import DomainSpec, Tier

MAX_PLACEMENT_TRIES = 200


@dataclass
class MpmScene:
    """Everything the MPM solver needs to start one trajectory."""

    position: np.ndarray  # [N, D] material particles
    velocity: np.ndarray  # [N, D]
    material: np.ndarray  # [N] material model codes (mpm_kernels.WATER, SAND, GOOP)
    particle_type: np.ndarray  # [N] particle type ids of the dataset
    container_lo: np.ndarray  # [D] container walls at rest
    container_hi: np.ndarray
    polygons: list[np.ndarray] = field(default_factory=list)  # static convex obstacles (2D), [V, 2] each
    kinematic: np.ndarray | None = None  # [K, D] boundary particles at rest
    shake: tuple[float, float] | None = None  # (amplitude, angular frequency) of horizontal shaking

    def offset(self, t: float) -> tuple[float, float]:
        """Horizontal container displacement and velocity at time t (zero unless shaken)."""
        if self.shake is None:
            return 0.0, 0.0
        amp, omega = self.shake
        return amp * math.sin(omega * t), amp * omega * math.cos(omega * t)

    def container(self, t: float) -> tuple[list[float], list[float], list[float]]:
        off, vel = self.offset(t)
        shift = np.zeros_like(self.container_lo)
        shift[0] = off
        velocity = [0.0] * len(shift)
        velocity[0] = vel
        return (self.container_lo + shift).tolist(), (self.container_hi + shift).tolist(), velocity

    def obstacle_sdf(self, grid: int) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance to the obstacles on the grid nodes (negative inside) and its unit gradient."""
        dim = self.position.shape[1]
        shape = (grid + 1,) * dim
        if not self.polygons:
            return np.full(shape, 1e3, np.float32), np.zeros((*shape, dim), np.float32)
        axes = np.meshgrid(*[np.arange(grid + 1) / grid] * dim, indexing="ij")
        points = np.stack(axes, axis=-1).reshape(-1, dim)
        sdf = union_sdf(points, self.polygons).reshape(shape)
        grad = np.stack(np.gradient(sdf, 1.0 / grid), axis=-1)
        grad /= np.maximum(np.linalg.norm(grad, axis=-1, keepdims=True), 1e-12)
        return sdf, grad

    def kinematic_positions(self, dt: float, frames: int) -> np.ndarray:
        """Boundary particle positions per stored frame, [frames + 1, K, D]."""
        dim = self.position.shape[1]
        if self.kinematic is None or len(self.kinematic) == 0:
            return np.zeros((frames + 1, 0, dim), np.float32)
        out = np.repeat(self.kinematic[None].astype(np.float64), frames + 1, axis=0)
        if self.shake is not None:
            out[:, :, 0] += np.array([self.offset(t * dt)[0] for t in range(frames + 1)])[:, None]
        return out.astype(np.float32)


# ----------------------------------------------------------------------------------------------
# Geometry
# ----------------------------------------------------------------------------------------------

def lattice_block(lo: np.ndarray, hi: np.ndarray, spacing: float) -> np.ndarray:
    """Particles on a regular lattice filling the box [lo, hi], cell-centred (2 per grid cell per dim)."""
    axes = [np.arange(a + spacing / 2, b, spacing) for a, b in zip(lo, hi, strict=True)]
    grids = np.meshgrid(*axes, indexing="ij")
    return np.stack(grids, axis=-1).reshape(-1, len(lo))


def block_scene(material: int, particle_type: int, block_lo: list[float], block_hi: list[float],
                bounds: list[list[float]], grid: int) -> MpmScene:
    """One block of one material at rest in a fixed container: the setup of the physics tests
    (water column, dam break, granular collapse)."""
    pts = lattice_block(np.asarray(block_lo, float), np.asarray(block_hi, float), 0.5 / grid)
    b = np.asarray(bounds, float)
    return MpmScene(pts, np.zeros_like(pts), np.full(len(pts), material), np.full(len(pts), particle_type),
                    b[:, 0].copy(), b[:, 1].copy())


def polygon_sdf(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Signed distance from 2D points to a convex polygon given counter-clockwise."""
    dist = np.full(len(points), np.inf)
    inside = np.ones(len(points), bool)
    for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        ab = b - a
        t = np.clip(((points - a) @ ab) / (ab @ ab), 0.0, 1.0)
        dist = np.minimum(dist, np.linalg.norm(points - (a + t[:, None] * ab), axis=1))
        cross = ab[0] * (points[:, 1] - a[1]) - ab[1] * (points[:, 0] - a[0])
        inside &= cross >= 0
    return np.where(inside, -dist, dist)


def union_sdf(points: np.ndarray, polygons: list[np.ndarray]) -> np.ndarray:
    return np.min([polygon_sdf(points, p) for p in polygons], axis=0)


def rectangle(center: np.ndarray, length: float, thickness: float, angle: float) -> np.ndarray:
    """A rotated rectangle as a counter-clockwise convex polygon."""
    c, s = math.cos(angle), math.sin(angle)
    u, n = np.array([c, s]) * length / 2, np.array([-s, c]) * thickness / 2
    return np.array([center - u - n, center + u - n, center + u + n, center - u + n])


def sample_boundary(polygons: list[np.ndarray], spacing: float, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Kinematic particles along the outline of the obstacles' union, inside the bounds.

    An edge point is kept only if just outside its edge (along the outward normal) is outside every
    obstacle: edges shared by touching obstacles (the joints of a random floor) are interior, not outline.
    """
    points, outward = [], []
    for poly in polygons:
        for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
            n = max(1, int(np.ceil(np.linalg.norm(b - a) / spacing)))
            points.append(a + np.linspace(0, 1, n, endpoint=False)[:, None] * (b - a))
            edge = (b - a) / np.linalg.norm(b - a)
            outward.append(np.broadcast_to([edge[1], -edge[0]], (n, 2)))  # right normal of a CCW edge
    pts, normals = np.concatenate(points), np.concatenate(outward)
    exposed = union_sdf(pts + 0.25 * spacing * normals, polygons) > 0.0
    keep = exposed & np.all((pts >= lo) & (pts <= hi), axis=1)
    return pts[keep]


# ----------------------------------------------------------------------------------------------
# Scene building
# ----------------------------------------------------------------------------------------------

SCENE_KEYS = frozenset({
    "blocks", "block_size", "block_materials", "initial_speed", "on_floor", "ramps", "ramp_length",
    "ramp_angle_deg", "ramp_thickness", "random_floor", "floor_height", "shake_amplitude", "shake_frequency",
    "container_width"})


def scene_params(spec: DomainSpec, tier: Tier) -> dict[str, Any]:
    """The spec's `[scene]` with the tier's overrides, every key checked (a typo must not be ignored)."""
    for where, table in (("scene", spec.scene), (f"tiers.{tier.name}.scene", tier.params.get("scene", {}))):
        unknown = sorted(set(table) - SCENE_KEYS)
        if unknown:
            raise ValueError(f"{spec.path}: key '{where}.{unknown[0]}': unknown scene key; expected some of "
                             f"{sorted(SCENE_KEYS)}")
    s = {**spec.scene, **tier.params.get("scene", {})}
    if ("shake_amplitude" in s) != ("shake_frequency" in s):
        raise ValueError(f"{spec.path}: key 'scene.shake_frequency': shaking needs both shake_amplitude and "
                         "shake_frequency")
    return s


def _uniform(rng: np.random.Generator, pair: Any) -> float:
    lo, hi = (pair, pair) if isinstance(pair, int | float) else pair
    return float(rng.uniform(lo, hi))


def _ramps(s: dict[str, Any], lo: np.ndarray, hi: np.ndarray, rng: np.random.Generator) -> list[np.ndarray]:
    count = int(rng.integers(s["ramps"][0], s["ramps"][1] + 1))
    polys = []
    for _ in range(count):
        length = _uniform(rng, s.get("ramp_length", [0.15, 0.3]))
        angle = math.radians(_uniform(rng, s.get("ramp_angle_deg", [-40.0, 40.0])))
        margin = 0.5 * length
        center = np.array([rng.uniform(lo[0] + margin, hi[0] - margin),
                           rng.uniform(lo[1] + 0.15 * (hi[1] - lo[1]), lo[1] + 0.6 * (hi[1] - lo[1]))])
        polys.append(rectangle(center, length, float(s.get("ramp_thickness", 0.03)), angle))
    return polys


def _floor(s: dict[str, Any], lo: np.ndarray, hi: np.ndarray, rng: np.random.Generator) -> list[np.ndarray]:
    segments = int(s["random_floor"])
    xs = np.linspace(lo[0] - 0.05, hi[0] + 0.05, segments + 1)
    heights = lo[1] + rng.uniform(*s.get("floor_height", [0.0, 0.2]), size=segments + 1)
    bottom = lo[1] - 0.1
    return [np.array([[xs[i], bottom], [xs[i + 1], bottom], [xs[i + 1], heights[i + 1]], [xs[i], heights[i]]])
            for i in range(segments)]


def build_scene(spec: DomainSpec, tier: Tier, models: dict[str, int], rng: np.random.Generator) -> MpmScene:
    """Draw one trajectory's initial condition. Deterministic given `rng`."""
    s = scene_params(spec, tier)
    dim = spec.dim
    grid = int(tier.params["grid"])
    spacing = 0.5 / grid  # two particles per grid cell per dimension, the usual MPM sampling
    bounds = np.asarray(spec.bounds, float)
    lo, hi = bounds[:, 0].copy(), bounds[:, 1].copy()
    shake = None
    if "shake_amplitude" in s:
        amp = _uniform(rng, s["shake_amplitude"])
        omega = 2 * math.pi * _uniform(rng, s["shake_frequency"])
        width = float(s.get("container_width", 0.7)) * (hi[0] - lo[0])
        # the container's walls sweep +-amp around the middle and must stay in the bounds
        amp = min(amp, 0.5 * (hi[0] - lo[0] - width))
        mid = 0.5 * (lo[0] + hi[0])
        lo[0], hi[0] = mid - width / 2, mid + width / 2
        shake = (amp, omega)

    polygons: list[np.ndarray] = []
    if dim == 2 and s.get("ramps"):
        polygons += _ramps(s, lo, hi, rng)
    if dim == 2 and s.get("random_floor"):
        polygons += _floor(s, lo, hi, rng)

    names = list(s.get("block_materials", list(models)))
    max_particles = int(tier.params.get("max_particles", 10**9))
    for _ in range(MAX_PLACEMENT_TRIES):
        blocks = _place_blocks(s, dim, lo, hi, spacing, polygons, rng)
        if blocks is not None and 0 < sum(len(b) for b in blocks) <= max_particles:
            break
    else:
        raise RuntimeError(f"{spec.path}: could not place blocks with at most {max_particles} particles "
                           f"in {MAX_PLACEMENT_TRIES} tries; check [scene] block_size and the tier's "
                           "max_particles")
    position, velocity, material, ptype = [], [], [], []
    vmax = float(s.get("initial_speed", 0.0))
    for block in blocks:
        name = names[int(rng.integers(len(names)))]
        position.append(block)
        velocity.append(np.broadcast_to(rng.uniform(-vmax, vmax, size=dim), block.shape))
        material.append(np.full(len(block), models[name]))
        ptype.append(np.full(len(block), spec.particle_types[name]))

    kinematic = None
    if polygons:
        kinematic = sample_boundary(polygons, spacing, bounds[:, 0], bounds[:, 1])
    if shake is not None:
        kinematic = _container_walls(lo, hi, spacing)
    return MpmScene(np.concatenate(position), np.concatenate(velocity), np.concatenate(material),
                    np.concatenate(ptype), lo, hi, polygons, kinematic, shake)


def _container_walls(lo: np.ndarray, hi: np.ndarray, spacing: float) -> np.ndarray:
    """Left, right and bottom walls of a 2D container as particle rows."""
    ys = np.arange(lo[1], hi[1] + 1e-9, spacing)
    xs = np.arange(lo[0] + spacing, hi[0] - spacing / 2, spacing)
    left = np.stack([np.full_like(ys, lo[0]), ys], 1)
    right = np.stack([np.full_like(ys, hi[0]), ys], 1)
    return np.concatenate([left, right, np.stack([xs, np.full_like(xs, lo[1])], 1)])


def _place_blocks(s: dict[str, Any], dim: int, lo: np.ndarray, hi: np.ndarray, spacing: float,
                  polygons: list[np.ndarray], rng: np.random.Generator) -> list[np.ndarray] | None:
    """Non-overlapping random boxes of particles, clear of the obstacles, or None if they do not fit."""
    count = int(rng.integers(s.get("blocks", [1, 1])[0], s.get("blocks", [1, 1])[1] + 1))
    margin = 2 * spacing
    floor_y = lo[1]
    placed: list[tuple[np.ndarray, np.ndarray]] = []
    blocks = []
    for _ in range(count):
        for _ in range(50):
            size = np.array([_uniform(rng, s.get("block_size", [0.1, 0.3])) for _ in range(dim)])
            size = np.minimum(size, hi - lo - 2 * margin)
            b_lo = np.array([rng.uniform(lo[d] + margin, hi[d] - margin - size[d]) for d in range(dim)])
            if s.get("on_floor"):
                b_lo[1] = floor_y + spacing / 2
            b_hi = b_lo + size
            if any(np.all(b_lo < p_hi + margin) and np.all(p_lo < b_hi + margin) for p_lo, p_hi in placed):
                continue
            pts = lattice_block(b_lo, b_hi, spacing)
            if polygons and np.min(union_sdf(pts, polygons)) < 2 * margin:
                continue
            placed.append((b_lo, b_hi))
            blocks.append(pts)
            break
        else:
            return None
    return blocks
