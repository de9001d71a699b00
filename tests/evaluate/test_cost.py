"""The evaluation-cost estimate counts what `evaluate` would do: every rollout step, every one-step window, every
distributional call, each at the cost measured for its own cloud."""

from __future__ import annotations

from pathlib import Path

import pytest

from gns_bench.config import EvalConfig
from gns_bench.data.format import load_split
from gns_bench.evaluate import cost
from gns_bench.model.simulator import LearnedSimulator


@pytest.fixture(scope="module")
def simulator(untrained: LearnedSimulator) -> LearnedSimulator:
    return untrained  # tests/evaluate/conftest.py


class Clock:
    """A clock the measured calls advance: a prediction by 1 ms a particle, MMD + OT by 1 us a particle pair."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_the_estimate_counts_every_step_window_and_distribution_call(simulator: LearnedSimulator, tiny_dataset: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    clock = Clock()
    real_predict = simulator.predict_next_position

    def predict(window, *args, **kwargs):
        clock.now += 1e-3 * window.shape[0]  # one ms a particle of the (possibly batched) window
        return real_predict(window, *args, **kwargs)

    def transport(x, y):
        clock.now += 1e-6 * len(x) * len(y)
        return 0.0, "emd"

    monkeypatch.setattr(simulator, "predict_next_position", predict)
    monkeypatch.setattr(cost.time, "perf_counter", clock)
    monkeypatch.setattr(cost.metrics, "mmd", lambda x, y, h: 0.0)
    monkeypatch.setattr(cost.metrics, "optimal_transport", transport)
    trajectories = load_split(tiny_dataset, "test")
    w = simulator.input_sequence_length
    config = EvalConfig(one_step_windows=4, distribution_steps=3)
    estimate = cost.evaluation_cost(simulator, trajectories, config)

    lengths = [t.num_steps - w for t in trajectories]
    assert estimate.rollout_steps == sum(lengths)
    assert estimate.rollout_seconds == pytest.approx(sum(n * 1e-3 * t.num_particles
                                                         for n, t in zip(lengths, trajectories, strict=True)))
    assert estimate.one_step_seconds == pytest.approx(sum(4 * 1e-3 * t.num_particles for t in trajectories))
    moving = [int((t.particle_type != 3).sum()) for t in trajectories]
    assert estimate.distribution_seconds == pytest.approx(sum(3 * 1e-6 * m * m for m in moving))
    assert estimate.seconds == pytest.approx(estimate.rollout_seconds + estimate.one_step_seconds
                                             + estimate.distribution_seconds)

    short = cost.evaluation_cost(simulator, trajectories, EvalConfig(max_trajectories=1, rollout_steps=5,
                                                                     distribution_steps=0))
    assert short.rollout_steps == 5 and short.distribution_seconds == 0.0
    assert short.rollout_seconds == pytest.approx(5 * 1e-3 * trajectories[0].num_particles)


def test_the_estimate_runs_on_the_real_clock(simulator: LearnedSimulator, tiny_dataset: Path) -> None:
    estimate = cost.evaluation_cost(simulator, load_split(tiny_dataset, "test"), EvalConfig(max_trajectories=1))
    assert estimate.rollout_steps > 0 and estimate.rollout_seconds > 0 and estimate.distribution_seconds > 0


def test_the_estimate_counts_only_the_metrics_configured(simulator: LearnedSimulator, tiny_dataset: Path) -> None:
    trajectories = load_split(tiny_dataset, "test")
    one_step = cost.evaluation_cost(simulator, trajectories, EvalConfig(max_trajectories=1, metrics=["one_step"]))
    assert one_step.one_step_seconds > 0 and one_step.rollout_seconds == 0 and one_step.distribution_seconds == 0
    rollout = cost.evaluation_cost(simulator, trajectories, EvalConfig(max_trajectories=1, metrics=["rollout"]))
    assert rollout.rollout_seconds > 0 and rollout.one_step_seconds == 0 and rollout.distribution_seconds == 0
