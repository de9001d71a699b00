"""Physical checks of the BOXBATH solver: position-based fluids with a shape-matched cube (seconds)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gns_bench.physics.pbd import RIGID_TYPE, WATER_TYPE, PBDParams, run_pbd, simulate
from gns_bench.physics.spec import load_domain_spec
from gns_bench.physics.sph_grid import SimulationError

DX = 0.04
DT = 0.005
POOL_BOX = np.array([[0.0, 0.32], [0.0, 0.48], [0.0, 0.32]])


def _pool_with_cube() -> tuple[np.ndarray, int, np.ndarray]:
    """A 0.2 m deep pool filling the floor of a narrow box and a 3x3x3 cube held just above it."""
    grid = np.stack(np.meshgrid(np.arange(8), np.arange(5), np.arange(8), indexing="ij"), -1).reshape(-1, 3)
    water = (grid + 0.5) * DX
    k = np.arange(3) - 1.0
    rest = np.stack(np.meshgrid(k, k, k, indexing="ij"), -1).reshape(-1, 3) * DX
    cube = np.array([0.16, 0.28, 0.16]) + rest
    return np.concatenate([water, cube]).astype(np.float32), len(water), rest.astype(np.float32)


def _pairwise(points: np.ndarray) -> np.ndarray:
    return np.linalg.norm(points[:, None] - points[None], axis=-1)


@pytest.fixture(scope="module")
def long_smoke_trajectory():
    """The smoke scene run for 0.5 s, long enough for the dam's wave to reach and push the cube."""
    spec = load_domain_spec("boxbath")
    smoke = spec.tier("smoke")
    spec = dataclasses.replace(spec, tiers={**spec.tiers, "smoke": dataclasses.replace(smoke, sequence_length=100)})
    return spec, simulate(spec, "smoke", np.random.default_rng(0))


def test_cube_stays_rigid_while_the_water_pushes_it(long_smoke_trajectory) -> None:
    _, traj = long_smoke_trajectory
    cube = traj.position[:, traj.particle_type == RIGID_TYPE].astype(np.float64)
    rest = _pairwise(cube[0])
    off_diagonal = ~np.eye(len(rest), dtype=bool)
    deviation = max(np.abs(_pairwise(frame)[off_diagonal] / rest[off_diagonal] - 1).max() for frame in cube)
    assert deviation < 0.01, deviation
    # ... and it was really pushed: the check above is not about a cube that never moved
    assert np.linalg.norm(cube[-1].mean(axis=0) - cube[0].mean(axis=0)) > 0.02


def test_trajectory_layout_bounds_and_small_steps(long_smoke_trajectory) -> None:
    spec, traj = long_smoke_trajectory
    pos, types = traj.position, traj.particle_type
    tier = spec.tier("smoke")
    assert pos.dtype == np.float32 and pos.shape[0] == 101 and pos.shape[2] == 3
    assert types.dtype == np.int64 and set(np.unique(types).tolist()) == {RIGID_TYPE, WATER_TYPE}
    assert (types == RIGID_TYPE).sum() == tier.params["cube_edge"] ** 3
    assert np.all(types[: (types == WATER_TYPE).sum()] == WATER_TYPE)  # water first, then the cube
    bounds = np.asarray(spec.bounds)
    assert np.all(np.isfinite(pos)) and np.all(pos >= bounds[:, 0]) and np.all(pos <= bounds[:, 1])
    assert np.linalg.norm(np.diff(pos, axis=0), axis=2).max() < spec.connectivity_radius / 2
    # the water is not squeezed: no two particles closer than a third of the spacing at the end
    water = pos[-1, types == WATER_TYPE]
    distances = _pairwise(water) + np.eye(len(water))
    assert distances.min() > DX / 3


@pytest.mark.parametrize(("relative_density", "floats"), [(0.5, True), (3.0, False)])
def test_light_cube_floats_and_heavy_cube_sinks(relative_density: float, floats: bool) -> None:
    position, num_water, rest = _pool_with_cube()
    params = PBDParams(bounds=POOL_BOX, gravity=(0.0, -9.81, 0.0), particle_spacing=DX,
                       cube_relative_density=relative_density)
    frames = run_pbd(params, position, num_water, rest, 150, DT)
    centre_y = frames[-20:, num_water:, 1].mean()
    surface = np.percentile(frames[-1, :num_water, 1], 95)
    half = 1.5 * DX  # the cube's half height (three particles of spacing dx)
    if floats:  # half as dense as water: it floats with its centre near the surface
        assert abs(centre_y - surface) < 0.5 * half, (centre_y, surface)
    else:  # three times as dense: it rests on the floor
        assert centre_y < POOL_BOX[1, 0] + half + 0.25 * DX, centre_y
    # the pool keeps its volume: its mean height is the initial 0.1 m plus half the rise that the cube's
    # submerged volume (Archimedes: the relative density, at most all of it) causes, within 5%
    floor_area = np.prod(np.ptp(POOL_BOX, axis=1)[[0, 2]])
    rise = min(relative_density, 1.0) * len(rest) * DX**3 / floor_area
    assert abs(frames[-1, :num_water, 1].mean() - (0.1 + rise / 2)) < 0.005


def test_same_seed_gives_identical_trajectories() -> None:
    spec = load_domain_spec("boxbath")
    a = simulate(spec, "smoke", np.random.default_rng(5))
    b = simulate(spec, "smoke", np.random.default_rng(5))
    c = simulate(spec, "smoke", np.random.default_rng(6))
    assert np.array_equal(a.position, b.position) and np.array_equal(a.particle_type, b.particle_type)
    assert a.position.shape != c.position.shape or not np.array_equal(a.position, c.position)


@pytest.mark.slow
def test_thread_count_does_not_change_the_bits(digests_across_threads) -> None:
    script = ("import hashlib, numpy as np; from gns_bench.physics.pbd import simulate; "
              "from gns_bench.physics.spec import load_domain_spec; "
              "t = simulate(load_domain_spec('boxbath'), 'smoke', np.random.default_rng(3)); "
              "print(hashlib.sha256(t.position.tobytes()).hexdigest())")
    assert len(digests_across_threads(script, ("1", "2"))) == 1


def test_blow_up_raises_naming_domain_and_frame() -> None:
    # A negative constraint softness over-corrects every projection: the run diverges within a frame.
    position, num_water, rest = _pool_with_cube()
    params = PBDParams(bounds=POOL_BOX, gravity=(0.0, -9.81, 0.0), particle_spacing=DX, relaxation=-0.9)
    with pytest.raises(SimulationError, match=r"unit-test-domain: simulation blew up at stored frame \d+"):
        run_pbd(params, position, num_water, rest, 20, DT, domain="unit-test-domain")
