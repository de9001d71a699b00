"""Seeding of the MPM material (geometry.py, scenes.py): i.i.d. uniform inside each shape at the density of
the lattice of half a grid cell (one particle per spacing^D), deterministic from the trajectory's rng."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

import gns_bench.physics.geometry as geometry
from gns_bench.data.format import KINEMATIC_PARTICLE_TYPE
from gns_bench.physics.geometry import blob_points, lattice_block, random_block
from gns_bench.physics.mpm import material_params
from gns_bench.physics.scenes import build_scene
from gns_bench.physics.spec import load_domain_spec


def _nearest_cv(points: np.ndarray) -> float:
    """Coefficient of variation of the nearest-neighbour distances: 0 on a lattice; for uniform random
    points ~0.52 in 2D and ~0.36 in 3D (Poisson process), a little more with a block's edges."""
    nearest = cKDTree(points).query(points, k=2)[0][:, 1]
    return float(nearest.std() / nearest.mean())


@pytest.mark.parametrize("lo, hi, spacing, cv_min", [
    ([0.1, 0.1], [0.3, 0.25], 1 / 128, 0.4),  # a WATERDROP-sized block, small tier
    ([0.13, 0.2], [0.2, 0.31], 1 / 64, 0.4),  # a smoke-tier block
    ([0.1, 0.1, 0.1], [0.3, 0.25, 0.2], 1 / 64, 0.3),  # a SAND-3D block
])
def test_random_block_is_random_at_the_lattice_density(lo: list[float], hi: list[float], spacing: float,
                                                        cv_min: float) -> None:
    lo_, hi_ = np.array(lo), np.array(hi)
    lattice = lattice_block(lo_, hi_, spacing)
    points = random_block(lo_, hi_, spacing, np.random.default_rng(7))
    assert _nearest_cv(lattice) == pytest.approx(0.0, abs=1e-9)
    assert _nearest_cv(points) > cv_min
    # the lattice's count, inside the lattice's cells (within half a spacing of the block's faces)
    assert len(points) == len(lattice)
    assert np.all(points >= lo_) and np.all(points <= lattice.max(axis=0) + spacing / 2)
    assert np.all(points.max(axis=0) > hi_ - spacing) and np.all(points.max(axis=0) < hi_ + spacing / 2)
    assert np.array_equal(points, random_block(lo_, hi_, spacing, np.random.default_rng(7)))
    assert not np.array_equal(points, random_block(lo_, hi_, spacing, np.random.default_rng(8)))


def test_blob_holds_the_lattice_count_of_its_shape_within_binomial_noise(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A blob's random particles are those of its box's random block inside its discs: a binomial count
    around the lattice's count in the same shape (the discs are drawn before the particles, so the same
    rng seed with the lattice in place of the random block gives the same shape)."""
    lo, hi, spacing = np.array([0.2, 0.3]), np.array([0.5, 0.55]), 1 / 128
    seeded = [blob_points(lo, hi, spacing, [3, 5], np.random.default_rng(i))[0] for i in range(20)]
    monkeypatch.setattr(geometry, "random_block", lambda lo, hi, spacing, rng: lattice_block(lo, hi, spacing))
    on_lattice = [blob_points(lo, hi, spacing, [3, 5], np.random.default_rng(i))[0] for i in range(20)]
    box = len(lattice_block(lo, hi, spacing))
    for points, reference in zip(seeded, on_lattice, strict=True):
        assert _nearest_cv(points) > 0.4
        p = len(reference) / box
        # 4 binomial standard deviations, plus the lattice's own rounding along the shape's outline
        assert abs(len(points) - len(reference)) < 4 * np.sqrt(box * p * (1 - p)) + 10
    total, expected = sum(map(len, seeded)), sum(map(len, on_lattice))
    assert abs(total / expected - 1) < 0.02


@pytest.mark.parametrize("domain, tier", [("goop", "smoke"), ("goop", "small"), ("waterramps", "small"),
                                          ("sand-3d", "smoke")])
def test_scene_material_is_seeded_at_random_and_deterministically(domain: str, tier: str) -> None:
    """Frame 0 of a domain's scene, every block together: random-like spacing, the same for the same rng
    seed. (Blocks do not touch, 2 spacings apart at least, so each particle's neighbour is in its block.)"""
    spec = load_domain_spec(domain).for_tier(tier)
    models = material_params(spec)[1]
    scene = build_scene(spec, spec.tier(tier), models, np.random.default_rng(3))
    again = build_scene(spec, spec.tier(tier), models, np.random.default_rng(3))
    assert np.array_equal(scene.position, again.position) and np.array_equal(scene.material, again.material)
    assert KINEMATIC_PARTICLE_TYPE not in scene.particle_type
    assert _nearest_cv(scene.position) > 0.3
