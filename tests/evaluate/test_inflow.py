"""Inflow: particles entering a running rollout (the paper's WaterRamps generalisation scene, Sec. 5.3)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from gns_bench.config import EvalConfig
from gns_bench.data.format import DatasetError, Trajectory, load_split, read_metadata, write_dataset
from gns_bench.evaluate import metrics
from gns_bench.evaluate.evaluate import evaluate, one_step_mse
from gns_bench.evaluate.rollout import RolloutState, rollout
from gns_bench.model.neighbours import radius_graph
from gns_bench.model.simulator import LearnedSimulator

BIRTHS = (9, 9, 12, 12)  # frames at which the four new particles enter


@pytest.fixture(scope="module")
def simulator(untrained: LearnedSimulator) -> LearnedSimulator:
    return untrained  # tests/evaluate/conftest.py


def with_inflow(traj: Trajectory, radius: float, births: tuple[int, ...] = BIRTHS) -> Trajectory:
    """The trajectory plus new particles entering next to moving ones; before birth each follows a
    straight prescribed path (its velocity history), as the generators store inflow."""
    moving = np.flatnonzero(traj.particle_type != 3)[: len(births)]
    new = traj.position[:, moving].copy()
    for j, b in enumerate(births):
        new[:, j] = traj.position[b, moving[j]] + np.array([0.4 * radius, 0.0], np.float32)
        new[: b, j] -= (np.arange(b, 0, -1)[:, None] * np.array([0.0, 1e-3], np.float32))
    position = np.concatenate([traj.position, new], axis=1)
    types = np.concatenate([traj.particle_type, traj.particle_type[moving]])
    birth = np.concatenate([np.zeros(traj.num_particles, np.int64), np.array(births, np.int64)])
    return Trajectory(position, types, traj.step_context, birth)


def test_particles_absent_before_birth_change_nothing(simulator: LearnedSimulator, tiny_dataset: Path) -> None:
    traj = load_split(tiny_dataset, "test")[0]
    inflow = with_inflow(traj, simulator.radius, births=(traj.num_steps - 1,) * 4)  # born after the rollout
    plain, grown = rollout(simulator, traj), rollout(simulator, inflow)
    n = traj.num_particles
    np.testing.assert_allclose(grown.predicted[:, :n], plain.predicted, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(grown.predicted[:, n:], inflow.position[6:, n:])  # they follow the data


def test_inflow_adds_particles_with_correct_graphs(simulator: LearnedSimulator, tiny_dataset: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    traj = with_inflow(load_split(tiny_dataset, "test")[0], simulator.radius)
    n = traj.num_particles - len(BIRTHS)
    graphs: list[tuple[torch.Tensor, torch.Tensor]] = []
    build = simulator.build_graph

    def recording(position: torch.Tensor, batch: torch.Tensor | None = None) -> torch.Tensor:
        edges = build(position, batch)
        graphs.append((position.clone(), edges))
        return edges

    monkeypatch.setattr(simulator, "build_graph", recording)
    states: list[RolloutState] = []
    result = rollout(simulator, traj, hooks=[states.append])
    w = simulator.config.input_sequence_length
    for step, (position, edges) in enumerate(graphs):
        frame = w + step
        present = traj.birth_step <= frame - 1
        assert position.shape[0] == int(present.sum())  # exactly the particles present at the input frame
        expected = radius_graph(position, simulator.radius, None, backend="scipy",
                                self_edges=simulator.config.self_edges)
        assert {tuple(e) for e in edges.T.tolist()} == {tuple(e) for e in expected.T.tolist()}
    born = [graphs[b - w + 1][0].shape[0] for b in sorted(set(BIRTHS))]
    assert born == [n + 2, n + 4]
    # a newborn's first window is its prescribed path; the particles already present keep their own history
    b = BIRTHS[0]
    state = states[b + 1 - w]  # the step whose input window ends at frame b
    np.testing.assert_array_equal(state.window[n].numpy(), traj.position[b - w + 1: b + 1, n])
    earlier = states[b - w]
    np.testing.assert_array_equal(state.window[:n, :-1].numpy(), earlier.window[:n, 1:].numpy())
    # once present, a newborn is predicted by the model, not copied from the data
    assert not np.allclose(result.predicted[-1, n], traj.position[-1, n], atol=1e-7)


def test_inflow_metrics_count_only_present_particles(simulator: LearnedSimulator, tiny_dataset: Path) -> None:
    traj = with_inflow(load_split(tiny_dataset, "test")[0], simulator.radius)
    result = rollout(simulator, traj)
    mask = result.scored_mask()
    w = simulator.config.input_sequence_length
    assert mask.shape == result.predicted.shape[:2]
    n = traj.num_particles - len(BIRTHS)
    assert not mask[BIRTHS[0] - w, n] and mask[BIRTHS[0] - w + 1, n]
    error = np.square(result.predicted.astype(np.float64) - result.ground_truth).mean(-1)  # [K, N]
    expected = sum(error[k][mask[k]].sum() for k in range(len(mask))) / mask.sum()
    assert metrics.rollout_mse(result.predicted, result.ground_truth, mask) == pytest.approx(expected, rel=1e-9)
    assert all(np.isfinite(one_step_mse(simulator, traj, device="cpu")))
    evaluation = evaluate(simulator, [traj], EvalConfig(distribution_steps=3), progress=False)
    assert np.isfinite(evaluation.metrics["rollout_mse"]) and np.isfinite(evaluation.metrics["mmd"])


def test_birth_step_round_trips_and_is_validated(tiny_dataset: Path, tmp_path: Path) -> None:
    meta = read_metadata(tiny_dataset)
    traj = with_inflow(load_split(tiny_dataset, "test")[0], meta.default_connectivity_radius)
    path = write_dataset(tmp_path / "inflow", meta, {"test": [traj]})
    loaded = load_split(path, "test")[0]
    np.testing.assert_array_equal(loaded.birth_step, traj.birth_step)
    bad = Trajectory(traj.position, traj.particle_type, traj.step_context, traj.birth_step + traj.num_steps)
    write_dataset(tmp_path / "bad", meta, {"test": [traj]})
    import h5py

    with h5py.File(tmp_path / "bad" / "test.h5", "a") as f:
        del f["00000/birth_step"]
        f["00000"].create_dataset("birth_step", data=bad.birth_step)
    with pytest.raises(DatasetError, match="birth_step"):
        load_split(tmp_path / "bad", "test")


def test_waiting_particles_do_not_trip_the_density_monitor(simulator: LearnedSimulator, tiny_dataset: Path) -> None:
    from gns_bench.evaluate.monitors import DensityMonitor

    traj = load_split(tiny_dataset, "test")[0]
    waiting = 3 * traj.num_particles  # far more than the monitor's 10 % share, all on one spot until they enter
    parked = np.broadcast_to(traj.position[0, :1], (traj.num_steps, waiting, 2)).copy()
    inflow = Trajectory(np.concatenate([traj.position, parked], axis=1),
                        np.concatenate([traj.particle_type, np.full(waiting, 5)]), traj.step_context,
                        np.concatenate([np.zeros(traj.num_particles, np.int64),
                                        np.full(waiting, traj.num_steps - 1, np.int64)]))
    moving = torch.from_numpy(inflow.particle_type != 3)
    monitor = DensityMonitor(moving, simulator.radius, every=1)
    assert rollout(simulator, inflow, 5, hooks=[monitor]).stopped_at is None
    everyone = Trajectory(inflow.position, inflow.particle_type, inflow.step_context)  # all present from the start
    stopped = rollout(simulator, everyone, 5, hooks=[monitor])
    assert stopped.stopped_at == 0 and "density_collapse" in stopped.stop_reason


def test_rollout_pictures_hide_particles_waiting_to_enter(simulator: LearnedSimulator, tiny_dataset: Path,
                                                          tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import matplotlib.axes

    from gns_bench.evaluate.plots import plot_rollout

    traj = with_inflow(load_split(tiny_dataset, "test")[0], simulator.radius)
    result = rollout(simulator, traj)
    drawn: list[int] = []
    scatter = matplotlib.axes.Axes.scatter
    monkeypatch.setattr(matplotlib.axes.Axes, "scatter",
                        lambda self, x, y, *a, **k: (drawn.append(len(x)), scatter(self, x, y, *a, **k))[1])
    plot_rollout(result, tmp_path / "inflow.png", num_frames=len(result.predicted))
    n = traj.num_particles - len(BIRTHS)
    w = simulator.config.input_sequence_length
    expected = [n + int(np.sum(np.array(BIRTHS) <= w + step)) for step in range(len(result.predicted))]
    assert drawn == [count for count in expected for _ in range(2)]  # ground truth and GNS, step by step


def test_rollout_animation_hides_particles_waiting_to_enter(simulator: LearnedSimulator, tiny_dataset: Path,
                                                            tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from matplotlib.collections import PathCollection

    from gns_bench.report.figures import rollout_gif

    traj = with_inflow(load_split(tiny_dataset, "test")[0], simulator.radius)
    result = rollout(simulator, traj)
    drawn: list[int] = []
    set_offsets = PathCollection.set_offsets
    monkeypatch.setattr(PathCollection, "set_offsets",
                        lambda self, xy: (drawn.append(int(np.isfinite(np.asarray(xy)).all(axis=1).sum())),
                                          set_offsets(self, xy))[1])
    rollout_gif(result, tmp_path / "inflow.gif", "inflow", max_frames=len(result.predicted))
    n = traj.num_particles - len(BIRTHS)
    w = simulator.config.input_sequence_length
    expected = {n + int(np.sum(np.array(BIRTHS) <= w + step)) for step in range(len(result.predicted))}
    counts = set(drawn[2:])  # the first two are the placeholders the scatters are built with
    assert counts == expected and len(expected) > 1  # particles appear as they are born, none before
    assert (tmp_path / "inflow.gif").stat().st_size > 0
