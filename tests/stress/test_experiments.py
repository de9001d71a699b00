"""Stress tests of a model: the measures' closed forms, and each test on the tiny domain."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from gns_bench.config import ModelConfig
from gns_bench.data.format import KINEMATIC_PARTICLE_TYPE, Trajectory, load_split, read_metadata
from gns_bench.evaluate import metrics
from gns_bench.stress import experiments


@pytest.fixture(scope="module")
def simulator(tiny_dataset: Path):
    from gns_bench.model.simulator import LearnedSimulator

    torch.manual_seed(0)
    meta = read_metadata(tiny_dataset)
    config = ModelConfig(latent_size=16, mlp_hidden_size=16, message_passing_steps=2,
                         connectivity_radius=meta.default_connectivity_radius)
    return LearnedSimulator(config, meta, 3e-4).eval()


def test_growth_rate_recovers_an_exponential() -> None:
    steps = np.arange(50)
    assert experiments.growth_rate(1e-4 * np.exp(0.07 * steps)) == pytest.approx(0.07, rel=1e-9)
    assert experiments.growth_rate(np.full(50, 3e-3)) == pytest.approx(0.0, abs=1e-12)
    assert np.isnan(experiments.growth_rate(np.array([np.nan, 0.0, 1.0])))


def test_rigidity_drift_is_zero_for_rigid_motion_and_sees_a_stretch() -> None:
    rng = np.random.default_rng(0)
    body = rng.uniform(0, 0.1, size=(20, 3))
    angle = 0.3
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    frames = np.stack([body, body @ rotation.T + 0.5, body * np.array([1.02, 1.0, 1.0])])
    drift = metrics.rigidity_drift(frames, np.ones(20, bool))  # the one definition, used by the stress test
    assert drift[0] == 0 and drift[1] < 1e-12
    assert 0.005 < drift[2] <= 0.02 + 1e-12  # RMS relative change: no pair stretches more than 2 %


def test_per_step_mse_matches_the_definition(simulator, tiny_dataset: Path) -> None:
    from gns_bench.evaluate.rollout import rollout

    traj = load_split(tiny_dataset, "test")[0]
    result = rollout(simulator, traj, 8)
    curve = experiments.per_step_mse(result, 10)
    moving = traj.particle_type != 3
    expected = np.square(result.predicted[3, moving].astype(np.float64) - result.ground_truth[3, moving]).mean()
    assert curve[3] == pytest.approx(expected, rel=1e-9)
    assert np.isnan(curve[8:]).all() and np.isfinite(curve[:8]).all()


def test_precision_bf16_diverges_more_than_fp32(simulator, tiny_dataset: Path) -> None:
    trajectories = load_split(tiny_dataset, "test")[:1]
    result = experiments.precision(simulator, trajectories, ["fp64", "fp32", "bf16"], steps=12)
    fp32, bf16 = result.metrics["divergence_final_fp32"], result.metrics["divergence_final_bf16"]
    assert 0 <= fp32 < 1e-5  # float32 round-off only
    assert bf16 > 10 * fp32
    assert simulator.vel_mean.dtype == torch.float32  # the fp64 reference leaves the model as it was


def test_perturbation_grows_from_its_initial_size(simulator, tiny_dataset: Path) -> None:
    traj = load_split(tiny_dataset, "test")[0]
    std = 1e-4
    shifted = Trajectory(traj.position + np.float32(std), traj.particle_type, traj.step_context)
    result = experiments.perturbation(simulator, [traj], std, solver_pairs=[(traj, shifted)], steps=10)
    model = np.asarray(result.curves["model_distance"])
    assert 0.3 * std < model[0] < 5 * std  # starts at the perturbation's size (sqrt(D) std for D=2)
    solver = np.asarray(result.curves["solver_distance"])
    np.testing.assert_allclose(solver, std * np.sqrt(2), rtol=1e-2)  # a constant shift neither grows nor shrinks
    assert result.metrics["solver_growth_rate"] == pytest.approx(0.0, abs=1e-3)


def test_scale_and_horizon_report_stability(simulator, tiny_dataset: Path) -> None:
    meta = read_metadata(tiny_dataset)
    trajectories = load_split(tiny_dataset, "test")[:1]
    wide = [[lo, lo + 2 * (hi - lo)] for lo, hi in meta.bounds]
    result = experiments.scale(simulator, {2: (trajectories, wide)}, trajectories[0].num_particles / 2, steps=5)
    assert result.metrics["x2/particle_ratio"] == pytest.approx(2.0)
    assert result.metrics["x2/stable_steps"] == 5 and result.metrics["largest_stable_factor"] == 2
    # Constant velocity over the 5 steps the GNS covered, not over the whole ground truth (issue #20).
    (traj,) = trajectories
    w = simulator.input_sequence_length
    cv = metrics.constant_velocity_rollout(traj.position[:w], 5)
    assert result.metrics["x2/steps_scored"] == 5 and traj.num_steps - w > 5
    assert result.metrics["x2/baseline_cv_same_steps_mse"] == pytest.approx(
        metrics.rollout_mse(cv, traj.position[w:w + 5], traj.particle_type != KINEMATIC_PARTICLE_TYPE), rel=1e-6)
    horizon = experiments.horizon(simulator, trajectories, training_length=5, steps=10)
    assert horizon.metrics["horizon_factor"] == 2 and len(horizon.curves["mse"]) == 10
    assert horizon.metrics["stable_steps"] <= 10
