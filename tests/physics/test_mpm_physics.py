"""Physical checks of the MLS-MPM solver against closed forms and experiments (smoke-sized, seconds)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gns_bench.physics.mpm import MaterialParams, SimulationError, run_scene
from gns_bench.physics.mpm_kernels import GOOP, SAND, WATER
from gns_bench.physics.scenes import block_scene

BOUNDS = [[0.1, 0.9], [0.1, 0.9]]
G = 9.81
DT = 0.0025


def _run(scene, params: MaterialParams, frames: int, grid: int, **kw) -> np.ndarray:
    return run_scene(scene, params, grid=grid, gravity=[0.0, -G], frame_dt=DT, frames=frames, bounds=BOUNDS,
                     **kw)


def test_water_column_at_rest_stays_at_rest() -> None:
    grid = 32
    scene = block_scene(WATER, 5, [0.1, 0.1], [0.9, 0.3], BOUNDS, grid)
    pos = _run(scene, MaterialParams(), frames=400, grid=grid)  # one second
    speed = np.linalg.norm(pos[-1] - pos[-2], axis=1) / DT
    # after settling, only weak acoustic ringing of the compressible fluid is left: < 1.5% of sqrt(g h)
    assert speed.mean() < 0.015 * math.sqrt(G * 0.2)
    # the free surface stays level (within a tenth of a particle spacing) and at its initial height
    x, y = pos[-1, :, 0], pos[-1, :, 1]
    bins = np.digitize(x, np.linspace(0.1, 0.9, 17))
    tops = np.array([y[bins == b].max() for b in np.unique(bins)])
    assert len(tops) == 16
    assert np.ptp(tops) < 0.1 * (0.5 / grid)
    assert abs(tops.mean() - scene.position[:, 1].max()) < 0.5 / grid
    assert pos[:, :, 1].min() >= BOUNDS[1][0]


# Martin & Moyce (1952), square-base column of width a and height 2a (n^2 = 2): surge front Z = x / a
# against T = t sqrt(2 g / a); the points of their tables up to T = 2 (as tabulated by Koshizuka & Oka 1996).
MARTIN_MOYCE_T = [0.41, 0.84, 1.19, 1.43, 1.63, 1.83, 1.98]
MARTIN_MOYCE_Z = [1.11, 1.22, 1.44, 1.67, 1.89, 2.11, 2.33]


@pytest.mark.parametrize("grid", [32, 64])
def test_dam_break_front_follows_martin_moyce(grid: int) -> None:
    a = 0.2
    scene = block_scene(WATER, 5, [0.1, 0.1], [0.1 + a, 0.1 + 2 * a], BOUNDS, grid)
    time_scale = math.sqrt(2 * G / a)
    frames = math.ceil(2.1 / time_scale / DT)
    pos = _run(scene, MaterialParams(), frames=frames, grid=grid)
    T = np.arange(frames + 1) * DT * time_scale
    Z = (pos[:, :, 0].max(axis=1) - BOUNDS[0][0]) / a
    simulated = np.interp(MARTIN_MOYCE_T, T, Z)
    errors = simulated / np.array(MARTIN_MOYCE_Z) - 1.0
    assert np.all(np.abs(errors) < 0.15), dict(zip(MARTIN_MOYCE_T, errors.round(3).tolist(), strict=True))
    assert np.all(np.diff(Z) >= -1e-3)  # the front never retreats during the surge


def _runout(friction_angle_deg: float) -> float:
    grid = 32
    scene = block_scene(SAND, 6, [0.1, 0.1], [0.25, 0.4], BOUNDS, grid)
    pos = _run(scene, MaterialParams(friction_angle_deg=friction_angle_deg), frames=240, grid=grid,
               wall_friction=0.5)
    return float(pos[-1, :, 0].max() - BOUNDS[0][0])


def test_granular_collapse_runout_decreases_with_friction_angle() -> None:
    runouts = [_runout(phi) for phi in (0.0, 30.0, 60.0)]
    # strictly decreasing, each by at least a grid cell, and a 60-degree column barely spreads
    assert runouts[0] - runouts[1] > 1 / 32 and runouts[1] - runouts[2] > 1 / 32, runouts
    assert runouts[2] < 2.5 * 0.15, runouts


def test_goop_spreads_less_than_water() -> None:
    grid = 32
    spread = {}
    for name, material in (("water", WATER), ("goop", GOOP)):
        scene = block_scene(material, 5 if material == WATER else 7, [0.4, 0.1], [0.6, 0.3], BOUNDS, grid)
        pos = _run(scene, MaterialParams(), frames=160, grid=grid)
        spread[name] = float(np.ptp(pos[-1, :, 0]))
    initial = 0.2 - 0.5 / grid
    assert spread["goop"] > initial + 0.01, spread  # goop does yield and flow under its own weight...
    assert spread["goop"] < 0.6 * spread["water"], spread  # ...but much less than water


def test_exploding_simulation_is_reported() -> None:
    grid = 32
    scene = block_scene(WATER, 5, [0.4, 0.4], [0.5, 0.5], BOUNDS, grid)
    scene.velocity[:] = [300.0, 0.0]  # far beyond what the CFL substep was chosen for
    with pytest.raises(SimulationError, match="stored frame 1"):
        _run(scene, MaterialParams(), frames=5, grid=grid, label="blowup")
