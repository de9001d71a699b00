"""Physical diagnostics against closed forms: a parabola is free fall at g, a block that stops in the air is not."""

from __future__ import annotations

import numpy as np
import pytest

from gns_bench.evaluate import diagnostics

G = np.array([0.0, -6e-5])
BOUNDS = [[0.1, 0.9], [0.1, 0.9]]


def parabola(frames: int, particles: int = 5, scale: float = 1.0, start_y: float = 0.8) -> np.ndarray:
    """[frames, N, 2] particles falling at `scale` g from rest: p_t = p_0 + t (t + 1) / 2 scale g."""
    t = np.arange(frames, dtype=float)[:, None, None]
    start = np.stack([np.linspace(0.3, 0.5, particles), np.full(particles, start_y)], axis=1)
    return start[None] + 0.5 * t * (t + 1) * scale * G


@pytest.mark.parametrize("scale", [1.0, 0.5, 0.0])
def test_rollout_gravity_ratio_is_the_predicted_share_of_g(scale):
    truth = parabola(40)
    predicted_all = parabola(40, scale=scale)
    w = 6
    # the model's rollout starts from the true window and falls at `scale` g from there
    predicted = truth[w - 1] + (predicted_all[w:] - predicted_all[w - 1])
    predicted += (truth[w - 1] - truth[w - 2]) * np.arange(1, 40 - w + 1)[:, None, None]  # keep the true velocity
    moving = np.ones(truth.shape[1], bool)
    ratio = diagnostics.rollout_gravity_ratio(truth[:w], predicted, truth[w:], moving, G)
    assert ratio == pytest.approx(scale, abs=1e-6)


def test_gravity_ratio_is_nan_without_free_fall():
    rest = np.full((20, 3, 2), 0.5)
    assert np.isnan(diagnostics.rollout_gravity_ratio(rest[:6], rest[6:], rest[6:], np.ones(3, bool), G))


def test_wall_pass_fraction_counts_particles_that_leave_once():
    frames = np.full((4, 4, 2), 0.5)
    frames[2, 1] = [0.5, 0.05]  # through the floor at one step
    frames[3, 2] = [0.95, 0.5]  # through the right wall
    moving = np.array([True, True, True, False])
    assert diagnostics.wall_pass_fraction(frames, BOUNDS, moving) == pytest.approx(2 / 3)
    assert diagnostics.wall_pass_fraction(np.full((4, 4, 2), 0.5), BOUNDS, moving) == 0.0


def test_wall_depth_is_the_furthest_step_past_a_wall_in_r():
    frames = np.full((4, 4, 2), 0.5)
    frames[2, 1] = [0.5, BOUNDS[1][0] - 0.03]  # 0.03 below the floor at one step
    frames[3, 2] = [BOUNDS[0][1] + 0.01, 0.5]  # 0.01 past the right wall
    frames[1, 3] = [0.5, BOUNDS[1][0] - 0.5]  # a kinematic particle far out: not counted
    moving = np.array([True, True, True, False])
    assert diagnostics.wall_depth(frames, BOUNDS, moving, 0.015) == pytest.approx(2.0)
    assert diagnostics.wall_depth(np.full((4, 4, 2), 0.5), BOUNDS, moving, 0.015) == 0.0


def test_centre_of_mass_fall_ratio_of_a_hovering_block_is_zero():
    truth = parabola(60)
    w = 6
    hover = np.repeat(truth[w - 1][None], 60 - w, axis=0)
    moving = np.ones(truth.shape[1], bool)
    hovering = diagnostics.centre_of_mass_errors(truth[:w], hover, truth[w:], moving, G, min_fall=0.015)
    assert hovering["com_fall_ratio"] == pytest.approx(0.0, abs=1e-9)
    assert hovering["com_error"] > 0.01
    exact = diagnostics.centre_of_mass_errors(truth[:w], truth[w:], truth[w:], moving, G, min_fall=0.015)
    assert exact == {"com_error": pytest.approx(0.0, abs=1e-12), "com_fall_ratio": pytest.approx(1.0)}
    # the truth barely moves: no fall to compare with
    still = np.full((20, 3, 2), 0.5)
    assert np.isnan(diagnostics.centre_of_mass_errors(still[:6], still[6:], still[6:], np.ones(3, bool), G,
                                                      min_fall=0.015)["com_fall_ratio"])


def test_steps_before_trip_is_the_first_trip_or_the_length():
    assert diagnostics.steps_before_trip(100, None, []) == 100
    assert diagnostics.steps_before_trip(40, 40, [12, 30]) == 12
    assert diagnostics.steps_before_trip(40, 25, []) == 25


def test_evaluation_logs_the_diagnostics(tiny_dataset):
    """Every evaluation carries the diagnostics: a model that predicts no acceleration at all (a block that
    hovers) scores gravity ratios near 0, the ground truth replayed (a perfect model) near 1."""
    import torch

    from gns_bench.config import EvalConfig, load_config, resolve_for_dataset
    from gns_bench.data.format import load_split, read_metadata
    from gns_bench.evaluate.evaluate import evaluate
    from gns_bench.train.checkpoints import build_simulator

    meta = read_metadata(tiny_dataset)
    config = resolve_for_dataset(load_config(None, ["model.latent_size=8", "model.mlp_hidden_size=8",
                                                    "model.message_passing_steps=1"]),
                                 meta.default_connectivity_radius)
    simulator = build_simulator(config, meta).eval()
    # zero the decoder: the network outputs 0, so the acceleration is acc_mean (about 0): nothing falls
    for p in simulator.network.decoder.parameters():
        torch.nn.init.zeros_(p)
    simulator.acc_mean.zero_()
    test = load_split(tiny_dataset, "test")[:1]
    evaluation = evaluate(simulator, test, EvalConfig(one_step_windows=2, distribution_steps=0), progress=False,
                          gravity=meta.gravity, walls=meta.walls)
    m = evaluation.metrics
    assert abs(m["gravity_ratio"]) < 1e-6 and abs(m["rollout_gravity_ratio"]) < 1e-6
    assert abs(m["held_gravity_ratio"]) < 1e-6 and abs(m["held_fall_ratio"]) < 1e-6
    assert {"com_error", "com_fall_ratio", "wall_pass_fraction", "wall_depth", "steps_before_trip",
            "landing_ratio"} <= set(m)
    assert m["steps_before_trip"] <= m["rollout_steps"]
    # the same model with gravity as its mean acceleration falls freely: ratio 1 on free-falling particles
    simulator.acc_mean.copy_(torch.tensor(meta.gravity))
    falling = evaluate(simulator, test, EvalConfig(one_step_windows=2, distribution_steps=0), progress=False,
                       gravity=meta.gravity, walls=meta.walls)
    assert falling.metrics["gravity_ratio"] == pytest.approx(1.0, abs=1e-3)
    assert falling.metrics["rollout_gravity_ratio"] == pytest.approx(1.0, abs=1e-3)
    assert falling.metrics["held_gravity_ratio"] == pytest.approx(1.0, abs=1e-3)
    assert falling.metrics["held_fall_ratio"] == pytest.approx(1.0, abs=1e-3)  # g k(k+1)/2, integrated as the truth
    assert falling.metrics["landing_ratio"] == pytest.approx(0.0, abs=1e-3)  # the balls it lets fall through the floor


def tiny_simulator(dataset):
    """An untrained one-block GNS on the tiny dataset, its metadata and first test trajectory: the tests below
    replace its prediction by a model of known behaviour."""
    from gns_bench.config import load_config, resolve_for_dataset
    from gns_bench.data.format import load_split, read_metadata
    from gns_bench.train.checkpoints import build_simulator

    meta = read_metadata(dataset)
    config = resolve_for_dataset(load_config(None, ["model.latent_size=8", "model.mlp_hidden_size=8",
                                                    "model.message_passing_steps=1"]),
                                 meta.default_connectivity_radius)
    return build_simulator(config, meta).eval(), meta, load_split(dataset, "test")[0]


def test_held_still_tells_a_model_that_reads_g_from_the_velocity_history(tiny_dataset, monkeypatch):
    """A model that extrapolates each particle's last acceleration from its own velocity history predicts g
    for a block in free fall on true windows, and nothing for the same block held still: the held-still ratio
    tells it from one that has learned g itself (1 on both, above)."""
    from gns_bench.evaluate.evaluate import held_fall_ratio, held_gravity_ratio, one_step_gravity_ratio

    simulator, meta, traj = tiny_simulator(tiny_dataset)

    def from_history(window, *args, **kwargs):  # p + v + (v - v_prev): the last acceleration again
        v, v_prev = window[:, -1] - window[:, -2], window[:, -2] - window[:, -3]
        return window[:, -1] + v + (v - v_prev)

    monkeypatch.setattr(simulator, "predict_next_position", from_history)
    assert one_step_gravity_ratio(simulator, traj, meta.gravity) == pytest.approx(1.0, abs=0.1)
    assert held_gravity_ratio(simulator, traj, meta.gravity) == pytest.approx(0.0, abs=1e-9)
    assert held_fall_ratio(simulator, traj, meta.gravity) == pytest.approx(0.0, abs=1e-9)


def test_held_fall_tells_a_model_that_pushes_a_block_back_once_it_moves(tiny_dataset, monkeypatch):
    """A model that gives g to material at rest and stops anything that moves (as a resting pile pushes back)
    scores 1 on the one-step held-still probe, yet a block let go from rest falls only every other step: over
    10 steps 5 g of the 55 g the truth falls (0.09). The rolled-out ratio sees what the first step hides."""
    import torch

    from gns_bench.evaluate.evaluate import held_fall_ratio, held_gravity_ratio

    simulator, meta, traj = tiny_simulator(tiny_dataset)
    g = torch.tensor(meta.gravity)

    def pushes_back(window, *args, **kwargs):  # at rest: fall at g; moving: stop (acceleration -v)
        v = window[:, -1] - window[:, -2]
        still = (v.abs().amax(dim=1, keepdim=True) < 1e-12)
        return window[:, -1] + v + torch.where(still, g.to(window.dtype), -v)

    monkeypatch.setattr(simulator, "predict_next_position", pushes_back)
    assert held_gravity_ratio(simulator, traj, meta.gravity) == pytest.approx(1.0, abs=1e-4)  # float32 positions
    assert held_fall_ratio(simulator, traj, meta.gravity) == pytest.approx(5 / 55, abs=1e-4)


def bounce(frames: int = 80, stiffness: float = 0.05, contact: float = 0.02) -> np.ndarray:
    """[frames, 3, 2] particles falling at g onto a floor that pushes back as a spring within `contact` of the
    lower bound, integrated as the model integrates (v' = v + a, p' = p + v')."""
    p = np.stack([np.linspace(0.3, 0.5, 3), np.array([0.16, 0.18, 0.2])], axis=1)
    v = np.zeros_like(p)
    out = [p.copy()]
    for _ in range(frames - 1):
        a = G + np.stack([np.zeros(3), stiffness * np.maximum(0.0, BOUNDS[1][0] + contact - p[:, 1])], axis=1)
        v = v + a
        p = p + v
        out.append(p.copy())
    return np.stack(out)


def test_landing_ratio_is_the_predicted_share_of_the_floors_push():
    frames = bounce()
    moving = np.ones(3, bool)
    truth = diagnostics.accelerations(frames)
    mask = diagnostics.landing_mask(frames, BOUNDS, G, 0.015, moving)
    assert mask.any() and not mask[:5].any()  # they land, and not while falling from rest
    assert (frames[1:-1][mask][:, 1] < BOUNDS[1][0] + 3 * 0.015).all()
    free_fall = np.broadcast_to(G, truth.shape)  # a model that lets them fall on at g
    for share, predicted in ((1.0, truth), (0.0, free_fall), (0.5, free_fall + 0.5 * (truth - free_fall))):
        assert diagnostics.landing_ratio(predicted, truth, mask, G) == pytest.approx(share, abs=1e-9)
    # the same fall without a floor lands nowhere, and one that ends just above the floor is not pushed there
    assert np.isnan(diagnostics.landing_ratio(truth, truth, diagnostics.landing_mask(
        parabola(40), BOUNDS, G, 0.015, np.ones(5, bool)), G))
    near = parabola(14, start_y=BOUNDS[1][0] + 0.01)
    near_mask = diagnostics.landing_mask(near, BOUNDS, G, 0.015, np.ones(5, bool))
    assert near_mask.any()
    assert np.isnan(diagnostics.landing_ratio(diagnostics.accelerations(near), diagnostics.accelerations(near),
                                              near_mask, G))
    # a kinematic particle never lands
    assert not diagnostics.landing_mask(frames, BOUNDS, G, 0.015, np.zeros(3, bool)).any()


def test_landing_mask_finds_the_floor_that_gravity_points_at():
    frames = bounce()
    flipped = frames.copy()
    flipped[..., 1] = 1.0 - frames[..., 1]  # the same bounce upside down: g upwards, floor at the upper bound
    moving = np.ones(3, bool)
    down = diagnostics.landing_mask(frames, BOUNDS, G, 0.015, moving)
    assert (diagnostics.landing_mask(flipped, BOUNDS, -G, 0.015, moving) == down).all()
    assert not diagnostics.landing_mask(flipped, BOUNDS, G, 0.015, moving).any()  # no floor below them


def test_landing_ratio_of_the_truth_is_one_and_of_free_fall_zero(tiny_dataset, monkeypatch):
    """On the tiny dataset's bouncing balls: a model that returns the truth's next frame scores 1, one that lets
    everything fall at g scores 0, one that keeps each particle's last acceleration (late by a frame at every
    contact) in between."""
    import torch

    from gns_bench.evaluate.evaluate import one_step_landing_ratio

    simulator, meta, traj = tiny_simulator(tiny_dataset)
    positions = torch.as_tensor(traj.position)
    n = traj.num_particles

    def oracle(window, *args, **kwargs):  # the truth's next frame of each window, found by its last frame
        last = window[:, -1].reshape(-1, n, window.shape[-1])
        frames = [int(((positions - frame.to(positions.dtype)).abs().amax(dim=(1, 2)) == 0).nonzero()[0])
                  for frame in last]
        return positions[[t + 1 for t in frames]].reshape(-1, window.shape[-1]).to(window.dtype)

    def falls(window, *args, **kwargs):
        return 2 * window[:, -1] - window[:, -2] + torch.tensor(meta.gravity, dtype=window.dtype)

    def from_history(window, *args, **kwargs):
        return 3 * window[:, -1] - 3 * window[:, -2] + window[:, -3]

    ratios = {}
    for name, model in (("oracle", oracle), ("falls", falls), ("history", from_history)):
        monkeypatch.setattr(simulator, "predict_next_position", model)
        ratios[name] = one_step_landing_ratio(simulator, traj, meta.gravity, meta.bounds)
    assert ratios["oracle"] == pytest.approx(1.0, abs=1e-3)  # float32 positions
    assert ratios["falls"] == pytest.approx(0.0, abs=1e-3)
    assert 0.0 < ratios["history"] < 0.9
