"""Report figures: rigid-body drift (the metric's closed forms, then the figure), rollouts of stopped runs,
units on the axes."""

from __future__ import annotations

from pathlib import Path

import matplotlib.image
import matplotlib.pyplot as plt
import numpy as np
import pytest
from PIL import Image

from gns_bench.evaluate import metrics
from gns_bench.evaluate.plots import MSE_UNIT
from gns_bench.evaluate.result import RolloutResult
from gns_bench.report import figures

RIGID, WATER = 0, 5


def rotation(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.fixture
def cube() -> np.ndarray:
    """A 5 x 5 x 5 lattice cube of spacing 0.02 at (0.3, 0.2, 0.4): 125 particles, 7750 pairs."""
    axis = np.arange(5) * 0.02
    return np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3) + [0.3, 0.2, 0.4]


# ----------------------------------------------------------------------------------------------
# metrics.rigidity_drift: closed forms
# ----------------------------------------------------------------------------------------------

def test_rigid_motion_does_not_drift(cube: np.ndarray) -> None:
    centre = cube.mean(0)
    frames = np.stack([(cube - centre) @ rotation(0.2 * t).T + centre + [0.01 * t, -0.003 * t, 0.0]
                       for t in range(6)])
    drift = metrics.rigidity_drift(frames, np.ones(len(cube), bool))
    assert drift.shape == (6,) and drift[0] == 0.0
    np.testing.assert_allclose(drift, 0.0, atol=1e-12)


@pytest.mark.parametrize("max_pairs", [None, 500])  # every pair, and a subsample: the same exact value
def test_uniform_scaling_by_s_drifts_by_s_minus_1(cube: np.ndarray, max_pairs: int | None) -> None:
    scales = np.array([1.0, 1.01, 0.9, 1.5, 2.0])
    centre = cube.mean(0)
    frames = np.stack([(cube - centre) @ rotation(s).T * s + centre for s in scales])  # scaled and turned
    drift = metrics.rigidity_drift(frames, np.ones(len(cube), bool), max_pairs=max_pairs)
    np.testing.assert_allclose(drift, np.abs(scales - 1.0), rtol=1e-12, atol=1e-15)


def test_two_particles_drift_by_their_relative_stretch() -> None:
    frames = np.array([[[0.0, 0.0], [1.0, 0.0]], [[0.0, 0.0], [0.0, 1.5]], [[0.2, 0.1], [0.2, 0.4]]])
    np.testing.assert_allclose(metrics.rigidity_drift(frames, np.ones(2, bool)), [0.0, 0.5, 0.7])


def test_only_the_masked_body_counts_and_a_broken_one_is_nan(cube: np.ndarray) -> None:
    rng = np.random.default_rng(0)
    water = rng.uniform(0, 1, size=(6, 40, 3))  # fluid moving anyhow
    frames = np.concatenate([np.broadcast_to(cube, (6, *cube.shape)), water], axis=1)
    mask = np.arange(frames.shape[1]) < len(cube)
    np.testing.assert_allclose(metrics.rigidity_drift(frames, mask), 0.0, atol=1e-12)
    frames = frames.copy()
    frames[3, 0] = np.nan
    assert np.isnan(metrics.rigidity_drift(frames, mask)[3])
    with pytest.raises(ValueError, match="at least 2"):
        metrics.rigidity_drift(frames, np.arange(frames.shape[1]) == 0)


def test_rigid_pairs_subsample_is_fixed_and_distinct() -> None:
    everything = {tuple(p) for p in metrics.rigid_pairs(300, None).tolist()}
    assert len(everything) == 300 * 299 // 2
    sample = metrics.rigid_pairs(300, 1000)
    assert sample.shape == (1000, 2) and (sample[:, 0] < sample[:, 1]).all()
    assert len({tuple(p) for p in sample.tolist()}) == 1000 and {tuple(p) for p in sample.tolist()} <= everything
    np.testing.assert_array_equal(sample, metrics.rigid_pairs(300, 1000))  # GNS and truth: the same pairs
    assert len(metrics.rigid_pairs(10, 1000)) == 45  # under the cap: all of them


# ----------------------------------------------------------------------------------------------
# The rigidity figure
# ----------------------------------------------------------------------------------------------

def boxbath_like(cube: np.ndarray, steps: int, stopped_at: int | None = None) -> RolloutResult:
    """The cube in water: the ground truth turns it rigidly, the GNS swells it by 1 % a step."""
    rng = np.random.default_rng(1)
    water = rng.uniform(0, 1, size=(30, 3))
    types = np.array([RIGID] * len(cube) + [WATER] * len(water))
    centre = cube.mean(0)

    def frame(body: np.ndarray) -> np.ndarray:
        return np.concatenate([body, water])

    window = np.stack([frame(cube)] * 3)
    truth = np.stack([frame((cube - centre) @ rotation(0.05 * t).T + centre) for t in range(1, steps + 1)])
    gns = np.stack([frame((cube - centre) * (1 + 0.01 * t) + centre) for t in range(1, steps + 1)])
    if stopped_at is not None:
        gns = gns[:stopped_at]
    return RolloutResult(gns, truth, window, types, stopped_at, "out_of_bounds at step 3: a particle left")


def test_rigidity_curves_start_at_the_last_input_frame(cube: np.ndarray) -> None:
    gns, truth = figures.rigidity_curves(boxbath_like(cube, 10), RIGID)
    np.testing.assert_allclose(gns, 0.01 * np.arange(11), atol=1e-12)  # step 0: the start, drift 0
    np.testing.assert_allclose(truth, 0.0, atol=1e-12)
    assert figures.rigidity_curves(boxbath_like(cube, 10), rigid_type=7) is None


def test_rigidity_figure_draws_gns_and_ground_truth(cube: np.ndarray, tmp_path: Path) -> None:
    rollouts = [boxbath_like(cube, 30), boxbath_like(cube, 30, stopped_at=12)]
    path = figures.rigidity_figure(rollouts, RIGID, tmp_path / "rigidity.png")
    image = matplotlib.image.imread(path)
    assert image.ndim == 3 and image.shape[1] > image.shape[0] > 100 and image.std() > 0
    water_only = [RolloutResult(r.predicted, r.ground_truth, r.initial_window, np.full_like(r.particle_type, WATER))
                  for r in rollouts]
    assert figures.rigidity_figure(water_only, RIGID, tmp_path / "none.png") is None
    assert not (tmp_path / "none.png").exists()


# ----------------------------------------------------------------------------------------------
# Rollouts and units
# ----------------------------------------------------------------------------------------------

def test_strip_draws_every_model_of_one_trajectory_and_refuses_two(cube: np.ndarray, tmp_path: Path) -> None:
    gns, cconv = boxbath_like(cube, 30), boxbath_like(cube, 30, stopped_at=12)
    path = figures.rollout_strip([("GNS", gns), ("CConv", cconv)], tmp_path / "strip.png", "BOXBATH")
    image = matplotlib.image.imread(path)
    single = matplotlib.image.imread(figures.rollout_png(gns, tmp_path / "single.png", "BOXBATH"))
    assert image.shape[0] > single.shape[0] and image.std() > 0  # one more row than GNS alone
    moved = RolloutResult(cconv.predicted, cconv.ground_truth, cconv.initial_window + 0.1, cconv.particle_type)
    with pytest.raises(ValueError, match="CConv's rollout does not start where the GNS's does"):
        figures.rollout_strip([("GNS", gns), ("CConv", moved)], tmp_path / "bad.png", "BOXBATH")


def test_gif_of_a_stopped_rollout_runs_the_whole_horizon(cube: np.ndarray, tmp_path: Path) -> None:
    result = boxbath_like(cube, 30, stopped_at=12)
    path = figures.rollout_gif(result, tmp_path / "stopped.gif", "stopped", max_frames=10, marks={5: "energy"})
    with Image.open(path) as gif:
        assert gif.n_frames == 11  # 10 over the 30 steps, and the last one before the stop
    png = figures.rollout_png(result, tmp_path / "stopped.png", "stopped")
    assert matplotlib.image.imread(png).std() > 0


def test_ablation_panels_name_their_units() -> None:
    stats = {m: [(1e-3, 1e-4, 2), (1e-2, 1e-3, 2)] for m, _ in figures.PANELS}
    fig = figures.draw_ablation("train.noise_std", [1e-4, 3e-4], stats, {"scale": "log", "default": 3e-4})
    assert [ax.get_ylabel() for ax in fig.axes][:2] == [f"MSE ({MSE_UNIT})"] * 2
    assert all(ax.get_ylabel() for ax in fig.axes)
    plt.close(fig)


def test_an_ablation_with_stopped_rollouts_draws_its_like_for_like_panels_in_two_rows() -> None:
    stats = {m: [(1e-3 * (i + 1), 1e-4, 2), (1e-2 * (i + 1), 1e-3, 2)]
             for i, (m, _) in enumerate(figures.PANELS[:2] + figures.STOPPED_PANELS + figures.PANELS[2:])}
    fig = figures.draw_ablation("train.noise_std", [1e-4, 3e-4], stats, {"scale": "log", "default": 3e-4})
    assert [ax.get_title() for ax in fig.axes] == [figures.PANEL_LABELS[m] for m in stats]
    assert len({ax.get_position().y0 for ax in fig.axes}) == 2  # six panels: two rows of three
    for ax, (metric, at_values) in zip(fig.axes, stats.items(), strict=True):
        assert ax.get_ylabel() == figures.PANEL_UNITS[metric]
        (errorbar,) = ax.containers
        np.testing.assert_allclose(errorbar.lines[0].get_ydata(), [s[0] for s in at_values])
    plt.close(fig)
