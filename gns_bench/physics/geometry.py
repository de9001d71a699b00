"""2D/3D geometry of the MPM scenes: particle seeding, blobs, convex obstacles and their signed distance.

Material is seeded at random: i.i.d. uniform positions inside each shape, as Taichi's `mpm99` does and as
the first frame of DeepMind's WaterRamps shows, at the density of the usual MPM lattice (2 particles per
grid cell per dimension, one per spacing^D). A lattice would survive into the flow (nearest-neighbour
distances all equal at frame 0, ordered patches in settled piles), a regularity the paper's data lacks.
"""

from __future__ import annotations

import math

import numpy as np


def _lattice_axes(lo: np.ndarray, hi: np.ndarray, spacing: float) -> list[np.ndarray]:
    """Cell centres per dimension of the lattice of `spacing` from `lo`: those below `hi`."""
    return [np.arange(a + spacing / 2, b, spacing) for a, b in zip(lo, hi, strict=True)]


def lattice_block(lo: np.ndarray, hi: np.ndarray, spacing: float) -> np.ndarray:
    """Particles on a regular lattice filling the box [lo, hi], cell-centred (2 per grid cell per dim):
    `random_block`'s count and the sampling on which a blob's solidity is measured; no scene seeds on it."""
    grids = np.meshgrid(*_lattice_axes(lo, hi, spacing), indexing="ij")
    return np.stack(grids, axis=-1).reshape(-1, len(lo))


def random_block(lo: np.ndarray, hi: np.ndarray, spacing: float, rng: np.random.Generator) -> np.ndarray:
    """As many particles as `lattice_block(lo, hi, spacing)` holds, i.i.d. uniform over that lattice's
    cells (the box from `lo` to `lo` + n_d spacing per dimension, within half a spacing of `hi`): the
    lattice's density, one particle per spacing^D, without its regularity."""
    cells = np.array([len(axis) for axis in _lattice_axes(lo, hi, spacing)])
    count = int(np.prod(cells))
    return np.asarray(lo, float) + rng.random((count, len(cells))) * (cells * spacing)


def blob_points(b_lo: np.ndarray, b_hi: np.ndarray, spacing: float, discs: list[int],
                rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """Particles inside a union of 3-5 overlapping discs, stretched to fill the box [b_lo, b_hi] (2D), and
    the blob's solidity. Each disc after the first overlaps a random earlier one (its centre at 0.6-0.95 of
    the sum of their radii), so the union is connected and usually non-convex.

    The particles are those of `random_block(b_lo, b_hi)` that fall inside: the block's density, a count
    binomial around the area's. The solidity is the shape's, measured on its lattice sampling (`solidity`),
    not on the random particles, whose convex hull depends on the draw (and misses more of a small shape)."""
    count = int(rng.integers(discs[0], discs[1] + 1))
    centres, radii = [np.zeros(2)], [float(rng.uniform(0.25, 0.45))]
    for _ in range(count - 1):
        parent = int(rng.integers(len(centres)))
        r = float(rng.uniform(0.2, 0.45))
        angle = rng.uniform(0.0, 2 * math.pi)
        reach = (radii[parent] + r) * rng.uniform(0.6, 0.95)
        centres.append(centres[parent] + reach * np.array([math.cos(angle), math.sin(angle)]))
        radii.append(r)
    c, r = np.array(centres), np.array(radii)
    box_lo, box_hi = (c - r[:, None]).min(axis=0), (c + r[:, None]).max(axis=0)

    def inside(pts: np.ndarray) -> np.ndarray:
        unit = box_lo + (pts - b_lo) / (b_hi - b_lo) * (box_hi - box_lo)  # back into the discs' frame
        return np.any(np.linalg.norm(unit[:, None, :] - c[None], axis=-1) < r[None], axis=1)

    shape = lattice_block(b_lo, b_hi, spacing)
    shape = shape[inside(shape)]
    pts = random_block(b_lo, b_hi, spacing, rng)
    return pts[inside(pts)], solidity(shape, spacing) if len(shape) else 1.0  # no cell inside: no blob


def solidity(points: np.ndarray, spacing: float) -> float:
    """Area of a 2D shape sampled on the lattice (`lattice_block`'s points inside it: particles x
    spacing^2) over the area of the convex hull of its cells (1 for a rectangle; clearly less for a
    non-convex blob)."""
    # only the lowest and the highest cell of each lattice column can reach the hull
    xs, column = np.unique(np.round(points[:, 0], 9), return_inverse=True)
    low, high = np.full(len(xs), np.inf), np.full(len(xs), -np.inf)
    np.minimum.at(low, column, points[:, 1])
    np.maximum.at(high, column, points[:, 1])
    h = 0.5 * spacing
    corners = [np.column_stack([xs + dx, ys]) for dx in (-h, h) for ys in (low - h, high + h)]
    return float(len(points) * spacing**2 / convex_hull_area(np.concatenate(corners)))


def convex_hull_area(points: np.ndarray) -> float:
    """Area of the convex hull of 2D points (Andrew's monotone chain, then the shoelace formula)."""
    pts = points[np.lexsort((points[:, 1], points[:, 0]))].tolist()  # by x, then y

    def half(chain: list[list[float]]) -> list[list[float]]:
        hull: list[list[float]] = []
        for p in chain:
            while len(hull) >= 2 and ((hull[-1][0] - hull[-2][0]) * (p[1] - hull[-2][1])
                                      - (hull[-1][1] - hull[-2][1]) * (p[0] - hull[-2][0])) <= 0:
                hull.pop()
            hull.append(p)
        return hull[:-1]

    hull = np.array(half(pts) + half(pts[::-1]))
    x, y = hull[:, 0], hull[:, 1]
    return float(0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


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
