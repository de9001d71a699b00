"""Free fall in a trajectory (`data/free_fall.py`): found where the truth accelerates at g, and held-still
windows whose target is the fall from rest the model's integration makes."""
from __future__ import annotations

import numpy as np
import pytest

from gns_bench.data import free_fall
from gns_bench.data.format import KINEMATIC_PARTICLE_TYPE, Trajectory

G = np.array([0.0, -6e-5])


def test_free_fall_mask_needs_three_frames_at_g():
    acc = np.repeat(G[None, None], 10, axis=0).copy()  # [10, 1, 2]
    acc[5, 0] = [0.0, 0.0]  # one frame of contact
    mask = free_fall.free_fall_mask(acc, G)[:, 0]
    assert not mask[0] and not mask[-1]  # no neighbour on one side
    assert not mask[4] and not mask[5] and not mask[6]  # the contact frame and its neighbours
    assert mask[1:4].all() and mask[7:9].all()


def _falls_then_lands(frames: int = 40, land: int = 20) -> Trajectory:
    """Three water particles thrown sideways that fall at g until frame `land`, then lie still; a wall particle
    (kinematic) that never moves."""
    t = np.arange(frames, dtype=np.float64)
    free = np.minimum(t, land)
    start = np.array([[0.3, 0.8], [0.32, 0.8], [0.34, 0.8], [0.1, 0.1]])
    position = np.repeat(start[None], frames, axis=0)
    position[:, :3] += (free * 1e-3)[:, None, None] * np.array([1.0, 0.0]) + \
        (0.5 * free * (free + 1))[:, None, None] * G
    types = np.array([5, 5, 5, KINEMATIC_PARTICLE_TYPE])
    return Trajectory(position.astype(np.float32), types)


def test_falling_frames_are_those_where_every_moving_particle_falls():
    traj = _falls_then_lands()
    frames = free_fall.falling_frames(traj, G)
    assert frames.min() == 2 and frames.max() == 18  # three frames at g around each; the landing's are not
    assert np.array_equal(frames, np.arange(2, 19))
    one_lands_early = Trajectory(traj.position.copy(), traj.particle_type)
    one_lands_early.position[10:, 0] = one_lands_early.position[10, 0]  # one particle stops at frame 10
    assert free_fall.falling_frames(one_lands_early, G).max() < 10
    assert free_fall.falling_frames(Trajectory(traj.position, traj.particle_type, birth_step=np.array([0, 5, 0, 0])),
                                    G).size == 0  # inflow: not every particle is there


@pytest.mark.parametrize(("future", "released"), [(1, 0), (3, 0), (1, 4)])
def test_a_held_window_is_at_rest_and_its_target_the_models_fall_from_rest(future, released):
    traj, window, frame = _falls_then_lands(), 6, 12
    held = free_fall.held_still(traj, frame, window, future, G, released)
    assert held.num_steps == window + released + future
    assert np.array_equal(held.position[:window], np.repeat(traj.position[frame: frame + 1], window, axis=0))
    # the model's integration (v' = v + a, p' = p + v') from rest at acceleration g reproduces every frame
    # after the release: the window's last `released` ones and the targets
    p, v = held.position[window - 1].astype(np.float64), np.zeros((4, 2))
    moving = traj.particle_type != KINEMATIC_PARTICLE_TYPE
    for k in range(released + future):
        v = v + np.where(moving[:, None], G, 0.0)
        p = p + v
        assert held.position[window + k] == pytest.approx(p, abs=1e-7)
    assert np.array_equal(held.position[:, ~moving], np.repeat(traj.position[frame: frame + 1, ~moving],
                                                               held.num_steps, axis=0))  # walls stay
