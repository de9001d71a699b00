"""Evaluation computes only what is configured (`eval.metrics`, `eval.monitors`), and `eval.neighbour_skin =
"auto"` picks Verlet lists by a probe without changing a rollout."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from gns_bench import autotune
from gns_bench.config import ConfigError, EvalConfig, load_config
from gns_bench.data.format import load_split, read_metadata
from gns_bench.evaluate import evaluate as evaluate_module
from gns_bench.evaluate.evaluate import evaluate
from gns_bench.model.simulator import LearnedSimulator

QUICK = dict(rollout_steps=12, one_step_windows=3, distribution_steps=2)
ONE_STEP = {"one_step_mse", "one_step_mse_moving"}
DISTRIBUTION = {"mmd", "ot", "ot_exact", "kinetic_energy_error"}
DIAGNOSTICS = {"gravity_ratio", "rollout_gravity_ratio", "wall_pass_fraction"}


@pytest.fixture
def trajectories(tiny_dataset: Path):
    return load_split(tiny_dataset, "test")[:2]


def test_each_metric_group_is_computed_only_when_listed(untrained: LearnedSimulator, tiny_dataset: Path,
                                                        trajectories, monkeypatch: pytest.MonkeyPatch) -> None:
    gravity = read_metadata(tiny_dataset).gravity
    full = evaluate(untrained, trajectories, EvalConfig(**QUICK), progress=False, gravity=gravity)
    assert ONE_STEP | DISTRIBUTION | DIAGNOSTICS | {"rollout_mse"} <= set(full.metrics)

    called: list[str] = []
    for name in ("one_step_mse", "distributional_metrics", "one_step_gravity_ratio", "physical_diagnostics"):
        original = getattr(evaluate_module, name)
        monkeypatch.setattr(evaluate_module, name,
                            lambda *a, _name=name, _original=original, **k: called.append(_name) or _original(*a, **k))

    only_rollout = evaluate(untrained, trajectories, EvalConfig(**QUICK, metrics=["rollout"]), progress=False,
                            gravity=gravity)
    assert not called
    assert not (ONE_STEP | DISTRIBUTION | DIAGNOSTICS) & set(only_rollout.metrics)
    assert only_rollout.metrics["rollout_mse"] == full.metrics["rollout_mse"]  # the same rollouts, scored alike
    np.testing.assert_array_equal(only_rollout.rollouts[1].predicted, full.rollouts[1].predicted)

    def no_rollout(*args, **kwargs):
        raise AssertionError("a one-step evaluation rolled out")

    monkeypatch.setattr(evaluate_module, "rollout", no_rollout)
    only_one_step = evaluate(untrained, trajectories, EvalConfig(**QUICK, metrics=["one_step"]), progress=False,
                             gravity=gravity)
    assert set(only_one_step.metrics) == ONE_STEP | {"num_trajectories"} and not only_one_step.rollouts
    for key in ONE_STEP:
        assert only_one_step.metrics[key] == full.metrics[key]


def test_a_one_step_evaluation_leaves_no_pictures_and_a_table(untrained: LearnedSimulator, trajectories,
                                                              tmp_path: Path) -> None:
    from gns_bench.pipeline import write_evaluation_artifacts

    evaluation = evaluate(untrained, trajectories, EvalConfig(**QUICK, metrics=["one_step"]), progress=False)
    written = write_evaluation_artifacts(evaluation, tmp_path, untrained.bounds.tolist(), "test")
    assert sorted(p.name for p in written) == ["test_per_trajectory.csv", "test_rollouts.npz"]
    assert "one_step_mse" in (tmp_path / "test_per_trajectory.csv").read_text().splitlines()[0]


def test_only_the_listed_monitors_run(untrained: LearnedSimulator, trajectories) -> None:
    traj = trajectories[0]
    every = evaluate_module.health_monitors(untrained, traj, 10)
    assert [m.name for m in every] == ["non_finite", "out_of_bounds", "energy_blowup", "density_collapse"]
    chosen = evaluate_module.health_monitors(untrained, traj, 10, which=["density_collapse", "non_finite"])
    assert [m.name for m in chosen] == ["non_finite", "density_collapse"]
    assert evaluate_module.health_monitors(untrained, traj, 10, which=False) == []

    # a bounds monitor that trips at once stops a rollout only when it runs
    tight = EvalConfig(rollout_steps=10, one_step_windows=1, distribution_steps=0, stop_on=["out_of_bounds"])
    far = [[0.45, 0.55], [0.45, 0.55]]  # walls the particles start outside of, well beyond 3 R
    stopped = evaluate(untrained, [traj], tight, progress=False, bounds=far)
    assert stopped.metrics["rollout_stopped"] == 1.0 and "out_of_bounds" in stopped.tags["rollouts_stopped"]
    unwatched = evaluate(untrained, [traj], EvalConfig(**{**tight.__dict__, "monitors": ["non_finite"]}),
                         progress=False, bounds=far)
    assert unwatched.metrics["rollout_stopped"] == 0.0 and unwatched.metrics["rollout_steps"] == 10


def test_selections_are_checked_where_they_are_configured() -> None:
    assert load_config(None, ['eval.metrics=["one_step"]']).eval.metrics == ["one_step"]
    assert load_config(None, ['eval.monitors=["non_finite"]']).eval.monitors == ["non_finite"]
    assert load_config(None, ["eval.monitors=false"]).eval.monitors is False
    with pytest.raises(ConfigError, match="eval.metrics.*list \"rollout\" with them"):
        load_config(None, ['eval.metrics=["one_step", "distribution"]'])
    with pytest.raises(ConfigError, match="eval.metrics"):
        load_config(None, ['eval.metrics=["mmd"]'])
    with pytest.raises(ConfigError, match="eval.metrics"):
        load_config(None, ["eval.metrics=[]"])
    with pytest.raises(ConfigError, match="eval.monitors"):
        load_config(None, ['eval.monitors=["escape"]'])
    with pytest.raises(ConfigError, match="eval.neighbour_skin"):
        load_config(None, ["eval.neighbour_skin=-0.1"])


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_the_skin_probe_keeps_the_fastest_only_past_its_margin() -> None:
    positions = torch.zeros(40, 5, 2)
    clock = FakeClock()
    cost = {0.0: 1.0, 0.1: 0.8, 0.25: 0.5, 0.5: 0.7}  # seconds a call, by skin in radii

    def finder(skin: float):
        def find(position: torch.Tensor) -> None:
            clock.now += cost[round(skin / 0.2, 6)]
        return find

    choice = autotune.choose_neighbour_skin(finder, positions, 0.2, clock=clock)
    assert choice.skin == pytest.approx(0.05) and choice.seconds_per_step[0.0] == pytest.approx(1.0)
    assert "skin 0.05 (0.25 R)" in choice.describe() and "none 1e+03 ms" in choice.describe()
    cost.update({0.25: 0.95, 0.1: 0.97, 0.5: 1.2})  # a 5% gain is inside the margin: no skin
    assert autotune.choose_neighbour_skin(finder, positions, 0.2, clock=clock).skin == 0.0


def test_auto_skin_rolls_out_as_a_fresh_search_does(untrained: LearnedSimulator, trajectories,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    config = EvalConfig(rollout_steps=30, one_step_windows=1, distribution_steps=0, monitors=False)
    fresh = evaluate(untrained, trajectories, EvalConfig(**{**config.__dict__, "neighbour_skin": 0.0}),
                     progress=False)
    assert "neighbour_skin" not in fresh.tags  # given, not probed
    probe = autotune.choose_neighbour_skin
    monkeypatch.setattr(autotune, "choose_neighbour_skin",  # any skin wins: the Verlet path is taken
                        lambda *args, **kwargs: probe(*args, **{**kwargs, "margin": 1e9}))
    auto = evaluate(untrained, trajectories, config, progress=False)
    assert auto.tags["neighbour_skin"].startswith("skin 0.") and "probed on true frames" in auto.tags["neighbour_skin"]
    for ours, theirs in zip(auto.rollouts, fresh.rollouts, strict=True):
        np.testing.assert_array_equal(ours.predicted, theirs.predicted)
