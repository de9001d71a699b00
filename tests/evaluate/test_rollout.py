"""Rollouts and metrics: kinematic particles follow the data, hooks stop a rollout, MSE closed forms."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from gns_bench.data.format import load_split, read_metadata
from gns_bench.evaluate import metrics
from gns_bench.evaluate.rollout import RolloutState, RolloutStopped, rollout
from gns_bench.model.simulator import LearnedSimulator


def test_kinematic_particles_follow_the_data(untrained: LearnedSimulator, tiny_dataset: Path) -> None:
    traj = load_split(tiny_dataset, "test")[0]
    kinematic = traj.particle_type == 3
    assert kinematic.any()
    traj.position[:, kinematic, 0] += np.linspace(0, 0.01, traj.num_steps, dtype=np.float32)[:, None]  # moving
    result = rollout(untrained, traj)
    assert result.predicted.shape == (traj.num_steps - 6, traj.num_particles, 2)
    np.testing.assert_array_equal(result.predicted[:, kinematic], traj.position[6:, kinematic])
    assert not np.allclose(result.predicted[:, ~kinematic], traj.position[6:, ~kinematic], atol=1e-6)


def test_hook_stops_a_rollout(untrained: LearnedSimulator, tiny_dataset: Path) -> None:
    traj = load_split(tiny_dataset, "test")[0]
    seen = []

    def stop_at_five(state: RolloutState) -> None:
        seen.append(state.step)
        if state.step == 5:
            raise RolloutStopped("test stop")

    result = rollout(untrained, traj, hooks=[stop_at_five])
    assert result.stopped_at == 5 and result.stop_reason == "test stop"
    assert result.predicted.shape[0] == 5 and seen == list(range(6))


def test_position_mse_closed_forms() -> None:
    rng = np.random.default_rng(0)
    truth = rng.normal(size=(7, 10, 2))
    assert metrics.position_mse(truth, truth) == 0.0
    assert metrics.position_mse(truth + 0.5, truth) == pytest.approx(0.25)
    shifted = truth.copy()
    shifted[:, 3] += 2.0  # only particle 3 off, by 2 in both dims
    mask = np.ones(10, dtype=bool)
    assert metrics.position_mse(shifted, truth, mask) == pytest.approx(4.0 / 10)
    mask[3] = False
    assert metrics.position_mse(shifted, truth, mask) == 0.0
    horizons = metrics.mse_at_horizons(truth + np.arange(7)[:, None, None], truth, horizons=(1, 3, 100))
    assert horizons == {1: 0.0, 3: pytest.approx((0 + 1 + 4) / 3)}


def test_constant_velocity_baseline_is_exact_for_uniform_motion() -> None:
    start, velocity = np.array([[0.1, 0.2]]), np.array([[0.01, -0.02]])
    frames = start[None] + np.arange(12)[:, None, None] * velocity[None]
    predicted = metrics.constant_velocity_rollout(frames[:6], 6)
    np.testing.assert_allclose(predicted, frames[6:], atol=1e-12)


def test_a_held_rollout_scores_a_stop_against_a_moving_truth() -> None:
    # particles moving at unit speed in x; the model's rollout stopped after 2 of 5 steps
    truth = np.arange(1, 6, dtype=np.float64)[:, None, None] * np.array([[[1.0, 0.0]]])
    window = np.zeros((3, 1, 2))
    held = metrics.held_rollout(truth[:2], window, 5)
    assert held.shape == (5, 1, 2) and (held[2:, 0, 0] == 2.0).all()  # frozen at the last covered frame
    assert metrics.rollout_mse(held, truth) == pytest.approx((0 + 0 + 1 + 4 + 9) / 10)  # x errors 1, 2, 3; y 0
    assert metrics.rollout_mse(metrics.held_rollout(truth, window, 5), truth) == 0.0  # a whole rollout: unchanged
    assert (metrics.held_rollout(truth[:0], window, 2) == 0.0).all()  # nothing predicted: the window's last frame


def test_a_stopped_rollout_holds_its_moving_particles_and_keeps_kinematic_ones_on_their_paths() -> None:
    from gns_bench.evaluate.evaluate import rollout_errors
    from gns_bench.evaluate.result import RolloutResult

    # particle 0 moving, particle 1 kinematic (type 3), both at unit speed in x; the rollout stopped after 2 of 4
    frames = np.arange(1, 9, dtype=np.float64)[:, None, None] * np.array([[[1.0, 0.0], [1.0, 0.0]]])
    window, truth = frames[:3], frames[3:7]
    result = RolloutResult(predicted=truth[:2].copy(), ground_truth=truth, initial_window=window,
                           particle_type=np.array([5, 3]), stopped_at=2, stop_reason="test")
    errors = rollout_errors(result, num_frames=8)  # the release's 8 - 3 - 1 = 4 steps
    # the moving particle is 1 and 2 behind over the two held steps, the kinematic one follows the data: (1 + 4) / 16
    assert errors["rollout_mse_held"] == pytest.approx(5 / 16)
    assert errors["mse_h1_held"] == 0.0 and errors["rollout_mse"] == 0.0  # the covered steps alone look perfect


def test_verlet_rollout_equals_fresh_search(untrained: LearnedSimulator, tiny_dataset: Path,
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    from gns_bench.model import neighbours
    from gns_bench.model.neighbours import VerletNeighbours

    made: list[VerletNeighbours] = []

    class Recorded(VerletNeighbours):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            made.append(self)

    monkeypatch.setattr(neighbours, "VerletNeighbours", Recorded)
    traj = load_split(tiny_dataset, "test")[0]
    fresh = rollout(untrained, traj, 30)
    assert not made
    reused = rollout(untrained, traj, 30, neighbour_skin=0.1)  # the data moves up to 0.026 a step, R = 0.1
    np.testing.assert_array_equal(reused.predicted, fresh.predicted)
    (lists,) = made  # the skin took the Verlet path: one list, searched every step, rebuilt only sometimes
    assert lists.calls == 30 and 1 < lists.rebuilds < 30, (lists.calls, lists.rebuilds)


def test_bf16_rollout_stays_close_to_fp32(untrained: LearnedSimulator, tiny_dataset: Path) -> None:
    traj = load_split(tiny_dataset, "test")[0]
    fp32 = rollout(untrained, traj, 10)
    bf16 = rollout(untrained, traj, 10, precision="bf16")
    assert bf16.predicted.dtype == np.float32
    difference = np.abs(bf16.predicted - fp32.predicted).max()
    assert 0 < difference < 1e-3, difference  # rounding shows, but positions do not drift far in 10 steps


def test_a_compiled_rollout_equals_the_eager_one_and_leaves_the_model_alone(untrained: LearnedSimulator,
                                                                            tiny_dataset: Path) -> None:
    from gns_bench.config import ConfigError, EvalConfig
    from gns_bench.evaluate.evaluate import evaluate
    from gns_bench.model.precision import compiled_for_inference

    trajectories = load_split(tiny_dataset, "test")[:1]
    base = dict(distribution_steps=0, monitors=False, rollout_steps=15, one_step_windows=3)
    eager = evaluate(untrained, trajectories, EvalConfig(**base), progress=False)
    compiled = evaluate(untrained, trajectories, EvalConfig(**base, compile=True), progress=False)
    np.testing.assert_allclose(compiled.rollouts[0].predicted, eager.rollouts[0].predicted, rtol=0, atol=1e-5)
    assert compiled.metrics["rollout_mse"] == pytest.approx(eager.metrics["rollout_mse"], rel=1e-3)
    assert untrained.network._compiled_call_impl is None  # a frozen copy was compiled, not the model
    assert compiled_for_inference(untrained).network._compiled_call_impl is not None
    with pytest.raises(ConfigError, match="eval.compile"):
        EvalConfig(compile=True, precision="fp64").validate()


@pytest.mark.parametrize("architecture", ["cconv", "dpi"])
def test_the_baselines_compiled_rollouts_equal_their_eager_ones(architecture: str, tiny_dataset: Path) -> None:
    from gns_bench.config import EvalConfig, load_config
    from gns_bench.evaluate.evaluate import evaluate
    from gns_bench.model.precision import compiled_for_inference
    from gns_bench.train.checkpoints import build_simulator

    torch.manual_seed(0)
    sizes = {"cconv": ["cconv.layer_channels=[8, 8, 8]"],
             "dpi": ["dpi.nf_relation=8", "dpi.nf_particle=8", "dpi.nf_effect=8"]}[architecture]
    config = load_config(None, [f"model.architecture={architecture}", *sizes])
    simulator = build_simulator(config, read_metadata(tiny_dataset)).eval()
    trajectories = load_split(tiny_dataset, "test")[:1]
    base = dict(distribution_steps=0, monitors=False, rollout_steps=8, one_step_windows=2)
    eager = evaluate(simulator, trajectories, EvalConfig(**base), progress=False)
    compiled = evaluate(simulator, trajectories, EvalConfig(**base, compile=True), progress=False)
    assert np.abs(eager.rollouts[0].predicted[-1] - trajectories[0].position[2]).max() > 0  # it moved
    np.testing.assert_allclose(compiled.rollouts[0].predicted, eager.rollouts[0].predicted, rtol=0, atol=1e-5)
    assert simulator.network._compiled_call_impl is None  # a frozen copy was compiled, not the model
    assert compiled_for_inference(simulator).network._compiled_call_impl is not None


def test_rollout_compile_auto_probes_once_then_uses_the_cache(untrained: LearnedSimulator, tiny_dataset: Path,
                                                              tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from gns_bench.config import EvalConfig, load_config
    from gns_bench.evaluate.evaluate import evaluate

    monkeypatch.setenv("GNS_BENCH_CACHE", str(tmp_path))
    assert load_config(None, ["eval.compile=auto"]).eval.compile == "auto"
    trajectories = load_split(tiny_dataset, "test")[:1]
    config = EvalConfig(distribution_steps=0, monitors=False, rollout_steps=10, one_step_windows=2, compile="auto")
    first = evaluate(untrained, trajectories, config, progress=False)
    choice = first.tags["rollout_compile"]  # e.g. "fp32 (probed: fp32 0.004 s, fp32+compile 0.002 s a step)"
    assert "(probed: fp32 " in choice and "fp32+compile " in choice
    again = evaluate(untrained, trajectories, config, progress=False)
    assert again.tags["rollout_compile"].split(" (")[0] == choice.split(" (")[0]
    assert "(cached: " in again.tags["rollout_compile"]


def test_static_edge_reuse_changes_nothing(untrained: LearnedSimulator, tiny_dataset: Path) -> None:
    traj = load_split(tiny_dataset, "test")[0]
    assert (traj.position == traj.position[:1]).all(axis=(0, 2)).sum() == 11  # the static floor row
    reused = rollout(untrained, traj, 20)
    fresh = rollout(untrained, traj, 20, reuse_static_edges=False)
    np.testing.assert_array_equal(reused.predicted, fresh.predicted)


def test_paper_and_moving_mse_definitions_by_hand(untrained: LearnedSimulator, tiny_dataset: Path) -> None:
    """The release's definitions (train.py): rollout MSE over `sequence_length - 6` steps and every particle
    (kinematic ones, on their true paths, add 0), one-step MSE over every particle of every window
    (kinematic ones with their unconstrained predictions); the `_moving` figures leave kinematic particles
    out, the rollout one over all T - 6 predicted steps."""
    from gns_bench.config import EvalConfig
    from gns_bench.evaluate.evaluate import evaluate

    traj = load_split(tiny_dataset, "test")[0]
    kinematic = traj.particle_type == 3
    n_all, n_moving = traj.num_particles, int((~kinematic).sum())
    assert 0 < n_moving < n_all
    evaluation = evaluate(untrained, [traj], EvalConfig(distribution_steps=0, monitors=False), progress=False)
    row = evaluation.per_trajectory[0]
    predicted, truth = evaluation.rollouts[0].predicted.astype(np.float64), traj.position[6:].astype(np.float64)
    seq = read_metadata(tiny_dataset).sequence_length
    assert traj.num_steps == seq + 1 and predicted.shape[0] == seq - 5
    error = np.square(predicted - truth)  # [T - 6, N, D]; kinematic rows are exactly 0
    assert not error[:, kinematic].any()
    paper = error[: seq - 6].sum() / ((seq - 6) * n_all * 2)
    moving = error[:, ~kinematic].sum() / ((seq - 5) * n_moving * 2)
    assert row["rollout_mse"] == pytest.approx(paper, rel=1e-9)
    assert row["rollout_mse_moving"] == pytest.approx(moving, rel=1e-9)
    # one step: every window ending at frames 5 .. T-2, predicted one by one from the clean window
    squares = []
    with torch.no_grad():
        for t in range(5, traj.num_steps - 1):
            window = torch.from_numpy(traj.position[t - 5: t + 1]).transpose(0, 1)
            nxt = untrained.predict_next_position(window, torch.from_numpy(traj.particle_type))
            squares.append(np.square(nxt.double().numpy() - traj.position[t + 1].astype(np.float64)))
    squares = np.stack(squares)  # [windows, N, D]
    assert squares[:, kinematic].mean() > 0  # kinematic particles' own predictions count
    assert row["one_step_mse"] == pytest.approx(squares.mean(), rel=1e-5)
    assert row["one_step_mse_moving"] == pytest.approx(squares[:, ~kinematic].mean(), rel=1e-5)


def test_one_step_measurements_do_not_depend_on_how_windows_are_batched(
        untrained: LearnedSimulator, tiny_dataset: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """One-step errors and the one-step gravity ratio batch windows up to a particle budget a forward (a CPU's
    caches, a GPU's launches): one window a forward, a few, or all in one give the same numbers."""
    from gns_bench.evaluate import evaluate as ev

    traj = load_split(tiny_dataset, "test")[0]
    gravity = read_metadata(tiny_dataset).gravity
    n = traj.num_particles
    seen = []
    for budget in (1, 3 * n, 10**9):
        monkeypatch.setitem(ev.ONE_STEP_PARTICLES, "cpu", budget)
        seen.append((ev.windows_per_forward(n, "cpu"), ev.one_step_mse(untrained, traj, 20),
                     ev.one_step_gravity_ratio(untrained, traj, gravity),
                     ev.held_gravity_ratio(untrained, traj, gravity)))
    assert [s[0] for s in seen] == [1, 3, 10**9 // n]
    for _, mse, ratio, held in seen[1:]:
        assert held == pytest.approx(seen[0][3], rel=1e-4, abs=1e-6)
        assert mse.one_step_mse == pytest.approx(seen[0][1].one_step_mse, rel=1e-5)
        assert mse.one_step_mse_moving == pytest.approx(seen[0][1].one_step_mse_moving, rel=1e-5)
        assert ratio == pytest.approx(seen[0][2], rel=1e-4, abs=1e-6)
    assert np.isfinite(seen[0][2])  # the tiny scene has particles in free fall to ask about
