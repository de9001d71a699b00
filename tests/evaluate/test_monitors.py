"""Each health monitor trips on a constructed bad state and not on a good one; a NaN stops a rollout; the
monitors outside `eval.stop_on` flag a rollout and let it run on."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from gns_bench.config import ModelConfig
from gns_bench.data.format import load_split, read_metadata
from gns_bench.evaluate.monitors import (
    BoundsMonitor,
    DensityMonitor,
    EnergyMonitor,
    FiniteMonitor,
    Flag,
    MonitorTripped,
    arm,
    close_share,
    default_monitors,
    flags,
)
from gns_bench.evaluate.rollout import RolloutState, rollout
from gns_bench.model.simulator import LearnedSimulator

R = 0.05


def state(position: np.ndarray, previous: np.ndarray | None = None, step: int = 0) -> RolloutState:
    previous = position if previous is None else previous
    window = torch.tensor(np.stack([previous] * 6, axis=1), dtype=torch.float32)
    return RolloutState(step, step + 6, torch.tensor(position, dtype=torch.float32), window)


def untrained_simulator(dataset: Path) -> tuple[LearnedSimulator, object]:
    """A small untrained GNS on `dataset` (seeded), with the dataset's metadata."""
    torch.manual_seed(0)
    meta = read_metadata(dataset)
    return LearnedSimulator(ModelConfig(latent_size=16, mlp_hidden_size=16, message_passing_steps=1,
                                        connectivity_radius=meta.default_connectivity_radius), meta,
                            3e-4).eval(), meta


@pytest.fixture
def grid() -> np.ndarray:
    axis = np.linspace(0.2, 0.8, 15)
    return np.stack(np.meshgrid(axis, axis), -1).reshape(-1, 2)  # spacing ~0.043, below R


def test_finite_monitor(grid: np.ndarray) -> None:
    FiniteMonitor()(state(grid))
    bad = grid.copy()
    bad[7, 1] = np.nan
    with pytest.raises(MonitorTripped, match="non_finite at step 3: 1 particles"):
        FiniteMonitor()(state(bad, step=3))


def test_bounds_monitor(grid: np.ndarray) -> None:
    monitor = BoundsMonitor(np.array([[0.0, 1.0], [0.0, 1.0]]), margin=3 * R)
    monitor(state(grid))
    slightly_out = grid.copy()
    slightly_out[0] = [-0.1, 0.5]  # within the margin
    monitor(state(slightly_out))
    far_out = grid.copy()
    far_out[0] = [0.5, 1.4]
    with pytest.raises(MonitorTripped) as info:
        monitor(state(far_out))
    assert info.value.monitor == "out_of_bounds" and info.value.value == pytest.approx(0.4, abs=1e-6)


def test_energy_monitor(grid: np.ndarray) -> None:
    moving = torch.ones(len(grid), dtype=torch.bool)
    step = np.full_like(grid, 0.002)  # R/25 a frame, like the paper's data
    monitor = EnergyMonitor(moving, initial_energy=0.5 * float((step**2).sum(1).mean()), radius=R)
    monitor(state(grid + step, grid))
    monitor(state(grid, grid))  # at rest: never trips (the floor)
    with pytest.raises(MonitorTripped, match="energy_blowup"):
        monitor(state(grid + 30 * step, grid))
    # a ground-truth reference with that energy at this step allows it
    fast = 0.5 * float(((30 * step) ** 2).sum(1).mean())
    EnergyMonitor(moving, monitor.initial_energy, R, reference=np.array([fast]))(state(grid + 30 * step, grid))


def test_density_monitor(grid: np.ndarray) -> None:
    moving = torch.ones(len(grid), dtype=torch.bool)
    monitor = DensityMonitor(moving, R)
    monitor(state(grid))
    collapsed = grid.copy()
    half = len(grid) // 2
    collapsed[:half] = grid[half: 2 * half] + 1e-4  # half the particles onto others
    with pytest.raises(MonitorTripped, match="density_collapse"):
        monitor(state(collapsed))
    DensityMonitor(moving, R, every=10)(state(collapsed, step=5))  # not a checking step


def test_density_monitor_needs_enough_close_particles(grid: np.ndarray) -> None:
    # 7 moving particles, 2 of them closer than 0.05 R (28.6%, as the inflow arena's first frames): noise
    few = grid[:7].copy()
    few[1] = few[0] + 1e-4
    DensityMonitor(torch.ones(7, dtype=torch.bool), R, every=1)(state(few))
    with pytest.raises(MonitorTripped, match="density_collapse"):  # it is the floor that holds it back
        DensityMonitor(torch.ones(7, dtype=torch.bool), R, every=1, min_close=2)(state(few))
    # the same share of 10 particles and more is a collapse
    many = grid[:35].copy()
    many[1:10:2] = many[0:9:2] + 1e-4
    assert round(close_share(many, np.ones(35, dtype=bool), 0.05 * R) * 35) == 10
    with pytest.raises(MonitorTripped, match="density_collapse"):
        DensityMonitor(torch.ones(35, dtype=torch.bool), R, every=1)(state(many))


def test_close_share_against_brute_force() -> None:
    rng = np.random.default_rng(0)
    cloud = rng.uniform(0, 0.05, size=(200, 2))
    moving = rng.random(200) < 0.7
    cutoff = 0.05 * R
    gap = np.linalg.norm(cloud[:, None] - cloud[None], axis=2) + np.eye(200) * 1e9
    assert close_share(cloud, moving, cutoff) == pytest.approx(np.mean(gap[moving].min(axis=1) < cutoff))
    assert 0 < close_share(cloud, moving, cutoff) < 1  # the case is not trivial


def test_density_trip_names_the_ground_truths_share(grid: np.ndarray) -> None:
    moving = torch.ones(len(grid), dtype=torch.bool)
    collapsed = grid.copy()
    quarter = len(grid) // 4
    collapsed[:quarter] = grid[quarter: 2 * quarter] + 1e-4  # a quarter onto others: half of them close
    truth = np.stack([grid, collapsed])  # the truth collapsed at rollout step 1 only
    monitor = DensityMonitor(moving, R, every=1, reference=truth)
    with pytest.raises(MonitorTripped, match=r"of another \(the ground truth: 0\.0%\)"):
        monitor(state(collapsed, step=0))
    share = close_share(collapsed, np.ones(len(grid), dtype=bool), 0.05 * R)
    with pytest.raises(MonitorTripped, match=rf"the ground truth: {share:.1%}".replace(".", r"\.")):
        monitor(state(collapsed, step=1))


def test_injected_nan_stops_the_rollout_at_that_step(tiny_dataset: Path) -> None:
    simulator, meta = untrained_simulator(tiny_dataset)
    traj = load_split(tiny_dataset, "test")[0]
    calls = {"n": 0}
    forward = simulator.forward

    def poisoned(*args, **kwargs):
        out = forward(*args, **kwargs)
        calls["n"] += 1
        if calls["n"] == 8:  # the 8th prediction (rollout step 7) goes bad for one particle
            out = out.clone()
            out[2, 0] = float("nan")
        return out

    simulator.forward = poisoned
    window = torch.from_numpy(traj.position[:6]).transpose(0, 1)
    moving = torch.from_numpy(traj.particle_type != 3)
    result = rollout(simulator, traj, hooks=default_monitors(meta.bounds, simulator.radius, window, moving))
    assert result.stopped_at == 7 and result.predicted.shape[0] == 7
    assert result.stopped_by.monitor == "non_finite" and np.isnan(result.stopped_by.position).any()
    assert np.isfinite(result.predicted).all()  # nothing after the bad state was kept


def test_tripped_monitor_is_logged_to_mlflow(tiny_dataset: Path, tmp_path: Path) -> None:
    from mlflow.tracking import MlflowClient

    from gns_bench import tracking
    from gns_bench.config import EvalConfig
    from gns_bench.evaluate.evaluate import evaluate
    from gns_bench.pipeline import _log_evaluation

    simulator, meta = untrained_simulator(tiny_dataset)
    forward, calls = simulator.forward, {"n": 0}

    def poisoned(*args, **kwargs):
        calls["n"] += 1
        out = forward(*args, **kwargs)
        return out * float("nan") if calls["n"] == 4 else out

    simulator.forward = poisoned
    evaluation = evaluate(simulator, load_split(tiny_dataset, "test")[:1], EvalConfig(one_step_windows=1),
                          progress=False)
    assert evaluation.metrics["rollout_stopped"] == 1.0
    # the baseline over the 3 steps the GNS covered, beside the one over the whole horizon
    from gns_bench.evaluate import metrics

    result = evaluation.rollouts[0]
    constant_velocity = metrics.constant_velocity_rollout(result.initial_window, result.ground_truth.shape[0])
    on_paths = np.where(result.moving_mask[None, :, None], constant_velocity, result.ground_truth)  # as the release
    assert evaluation.metrics["baseline_cv_same_steps_mse"] == pytest.approx(
        metrics.rollout_mse(on_paths[:3], result.ground_truth[:3]))
    assert evaluation.metrics["baseline_cv_same_steps_mse"] < evaluation.metrics["baseline_cv_rollout_mse"]
    # the stopped rollout counted over the whole horizon: its moving particles held at the last covered frame
    truth, k = result.ground_truth, result.predicted.shape[0]
    held = np.concatenate([result.predicted, np.repeat(result.predicted[-1:], truth.shape[0] - k, axis=0)])
    held = np.where(result.moving_mask[None, :, None], held, truth)
    steps = load_split(tiny_dataset, "test")[0].num_steps - result.initial_window.shape[0] - 1  # the release's
    assert evaluation.metrics["rollout_mse_held"] == pytest.approx(metrics.rollout_mse(held[:steps], truth[:steps]))
    assert evaluation.metrics["mse_h20_held"] == pytest.approx(
        metrics.position_mse(held[:20], truth[:20], result.moving_mask))
    assert "mse_h20" not in evaluation.metrics  # the cut-short rollout never reached step 20
    with tracking.start_run("monitor-test", "nan") as run:
        _log_evaluation(run, evaluation, tmp_path, meta.bounds, "test")
    logged = MlflowClient(tracking_uri=tracking.tracking_uri()).get_run(run.run_id)
    assert "non_finite at step 3" in logged.data.tags["test/rollouts_stopped"]
    assert logged.data.metrics["test/rollout_stopped"] == 1.0
    saved = np.load(tmp_path / "test_monitor_states.npz")
    assert str(saved["00000/monitor"]) == "non_finite" and int(saved["00000/step"]) == 3
    moving = load_split(tiny_dataset, "test")[0].particle_type != 3
    assert np.isnan(saved["00000/position"][moving]).all()  # the bad state itself, as the monitor saw it
    assert np.isfinite(saved["00000/position"][~moving]).all()  # kinematic particles come from the data


def test_monitor_names_in_the_config_are_the_monitors(grid: np.ndarray) -> None:
    import typing

    from gns_bench.config import ConfigError, MonitorName, config_from_dict

    window = torch.tensor(np.stack([grid] * 6, axis=1), dtype=torch.float32)
    monitors = default_monitors([[0.0, 1.0], [0.0, 1.0]], R, window, torch.ones(len(grid), dtype=torch.bool))
    assert {m.name for m in monitors} == set(typing.get_args(MonitorName))
    with pytest.raises(ConfigError, match="eval.stop_on.*walls"):
        config_from_dict({"eval": {"stop_on": ["walls"]}}, "test")


def test_a_flagging_monitor_lets_the_rollout_run_on(tiny_dataset: Path) -> None:
    """Outside `stop_on` a monitor records its first trip and the rollout runs the whole horizon."""
    simulator, meta = untrained_simulator(tiny_dataset)
    traj = load_split(tiny_dataset, "test")[0]
    far = np.array([[5.0, 6.0]] * meta.dim)  # every particle is far outside these bounds

    stopping = arm([BoundsMonitor(far, 3 * R)], ["out_of_bounds"])
    assert rollout(simulator, traj, 10, hooks=stopping).stopped_at == 0
    assert flags(stopping) == []

    flagging = arm([BoundsMonitor(far, 3 * R), FiniteMonitor()], ["non_finite"])
    assert isinstance(flagging[0], Flag) and isinstance(flagging[1], FiniteMonitor)
    result = rollout(simulator, traj, 10, hooks=flagging)
    assert result.stopped_at is None and result.predicted.shape[0] == 10
    (trip,) = flags(flagging)
    assert trip.monitor == "out_of_bounds" and trip.step == 0  # the first trip, kept; later ones not re-raised


def test_evaluation_flags_without_stopping_by_default(tiny_dataset: Path) -> None:
    from gns_bench.config import EvalConfig
    from gns_bench.evaluate.evaluate import evaluate

    simulator, meta = untrained_simulator(tiny_dataset)
    trajectories = load_split(tiny_dataset, "test")[:1]
    far = [[5.0, 6.0]] * meta.dim
    flagged = evaluate(simulator, trajectories, EvalConfig(one_step_windows=1, rollout_steps=8), progress=False,
                       bounds=far)
    assert flagged.metrics["rollout_flagged"] == 1.0 and flagged.metrics["rollout_stopped"] == 0.0
    assert flagged.metrics["rollout_steps"] == 8.0
    assert "trajectory 0: out_of_bounds at step 0" in flagged.tags["rollouts_flagged"]
    stopped = evaluate(simulator, trajectories, EvalConfig(one_step_windows=1, rollout_steps=8,
                                                           stop_on=["out_of_bounds"]), progress=False, bounds=far)
    assert stopped.metrics["rollout_stopped"] == 1.0 and stopped.metrics["rollout_steps"] == 0.0
    assert "rollouts_flagged" not in stopped.tags


def test_a_horizon_only_later_trajectories_reach_is_summarised_and_written(tiny_dataset: Path, tmp_path: Path) -> None:
    """The first rollout stops before step 10, the second reaches it: `mse_h10` is the second's, and the
    per-trajectory table has the column, empty for the first (a bug once failed a whole run on this)."""
    import csv

    from gns_bench.config import EvalConfig
    from gns_bench.evaluate.evaluate import evaluate
    from gns_bench.pipeline import write_evaluation_artifacts

    simulator, meta = untrained_simulator(tiny_dataset)
    forward, calls = simulator.forward, {"n": 0}

    def poisoned(*args, **kwargs):
        calls["n"] += 1
        out = forward(*args, **kwargs)
        return out * float("nan") if calls["n"] == 4 else out  # the first rollout's 4th step goes bad

    simulator.forward = poisoned
    evaluation = evaluate(simulator, load_split(tiny_dataset, "test")[:2],
                          EvalConfig(one_step_windows=1, distribution_steps=0, rollout_steps=12), progress=False)
    first, second = evaluation.per_trajectory
    assert "mse_h10" not in first and "mse_h10" in second
    assert evaluation.metrics["mse_h10"] == pytest.approx(second["mse_h10"])
    write_evaluation_artifacts(evaluation, tmp_path, meta.bounds, "test")
    with (tmp_path / "test_per_trajectory.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert rows[0]["mse_h10"] == "" and float(rows[1]["mse_h10"]) == pytest.approx(second["mse_h10"])
