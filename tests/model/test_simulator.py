"""The learned simulator: features, invariances, integration, noise, and every ablation switch."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from gns_bench.config import ModelConfig
from gns_bench.data.format import Metadata
from gns_bench.model.features import acceleration_from_next_position, integrate
from gns_bench.model.network import InteractionNetwork
from gns_bench.model.noise import noisy_training_pair, random_walk_position_noise
from gns_bench.model.simulator import LearnedSimulator

SMALL = dict(latent_size=32, mlp_hidden_size=32, message_passing_steps=3, connectivity_radius=0.2)  # R of `metadata`


def metadata(walls: bool, types: int = 2, context: int = 0, gravity: bool = False) -> Metadata:
    meta = Metadata(bounds=[[0.0, 1.0], [0.0, 1.0]], sequence_length=10, default_connectivity_radius=0.2, dim=2,
                    dt=1.0, vel_mean=[0.0, -1e-3], vel_std=[1e-2, 1e-2], acc_mean=[0.0, -1e-4],
                    acc_std=[1e-3, 1e-3], particle_types=dict(list({"water": 5, "kinematic": 3}.items())[:types]),
                    walls=walls, gravity=[0.0, -2e-4] if gravity else None)
    if context:
        meta.context_mean, meta.context_std = [0.5] * context, [0.1] * context
    return meta


def window(n: int = 40, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    start = torch.rand(n, 1, 2, generator=g) * 0.5 + 0.25
    velocity = torch.randn(n, 1, 2, generator=g) * 0.01
    steps = torch.arange(6, dtype=torch.float32)[None, :, None]
    types = torch.where(torch.arange(n) < n - 5, 5, 3)
    return start + steps * velocity, types


@pytest.mark.parametrize("encoding, invariant", [("relative", True), ("absolute", False)])
def test_translation_invariance(encoding: str, invariant: bool) -> None:
    torch.manual_seed(0)
    # without wall features: they see the bounds, which a shift moves the particles towards
    config = ModelConfig(**SMALL, position_encoding=encoding, wall_features="walls_only")
    sim = LearnedSimulator(config, metadata(walls=False), 3e-4)
    w, types = window()
    shift = torch.tensor([0.13, -0.07])
    with torch.no_grad():
        a = sim(w, types)
        b = sim(w + shift, types)
    assert a.abs().mean() > 1e-3
    if invariant:
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)
    else:
        assert (a - b).abs().max() > 1e-2


def test_integration_round_trip() -> None:
    w, _ = window()
    true_next = w[:, -1] + torch.randn(w.shape[0], 2) * 1e-3
    acceleration = acceleration_from_next_position(w, true_next)
    torch.testing.assert_close(integrate(w, acceleration), true_next, rtol=0, atol=1e-7)
    # semi-implicit Euler: v' = v + a, p' = p + v'
    v = w[:, -1] - w[:, -2]
    torch.testing.assert_close(integrate(w, acceleration), w[:, -1] + (v + acceleration))


def test_random_walk_noise_statistics() -> None:
    g = torch.Generator().manual_seed(0)
    sigma = 3e-4
    noise = random_walk_position_noise((200_000, 6, 2), sigma, g)
    assert torch.all(noise[:, 0] == 0), "the first input position gets no noise"
    velocity_noise = noise[:, 1:] - noise[:, :-1]
    last_std = float(velocity_noise[:, -1].std())
    assert abs(last_std / sigma - 1) < 0.05
    first_std = float(velocity_noise[:, 0].std())
    assert abs(first_std / (sigma / 5**0.5) - 1) < 0.05  # a random walk: std grows as sqrt(step)


def test_noise_masks_kinematic_particles() -> None:
    w, types = window()
    noise = random_walk_position_noise(tuple(w.shape), 1e-2, torch.Generator().manual_seed(1), mask=types != 3)
    noisy, target = noisy_training_pair(w, w[:, -1], noise)
    kinematic = types == 3
    assert torch.equal(noisy[kinematic], w[kinematic]) and torch.equal(target[kinematic], w[kinematic, -1])
    assert not torch.equal(noisy[~kinematic], w[~kinematic])


@pytest.mark.parametrize("correction", [0.0, 1.0, 0.5])
def test_corrected_targets(correction: float) -> None:
    """Integrating the corrected target from the noisy window lands on p_{t+1} + (1 - alpha) n_t:
    alpha = 0 gives the clean next velocity, alpha = 1 the clean next position."""
    g = torch.Generator().manual_seed(2)
    w, _ = window(seed=3)
    true_next = w[:, -1] + (w[:, -1] - w[:, -2]) + 1e-4
    noisy, target = noisy_training_pair(w, true_next, random_walk_position_noise(tuple(w.shape), 3e-4, g), correction)
    reached = integrate(noisy, acceleration_from_next_position(noisy, target))
    last_noise = noisy[:, -1] - w[:, -1]
    torch.testing.assert_close(reached, true_next + (1 - correction) * last_noise, rtol=0, atol=1e-7)
    if correction == 0.0:  # the corrected velocity equals the true next velocity
        torch.testing.assert_close(reached - noisy[:, -1], true_next - w[:, -1], rtol=0, atol=1e-7)


def test_split_edge_layer_equals_concatenation() -> None:
    torch.manual_seed(0)
    block = InteractionNetwork(16, 24, 2, global_latent=False)
    nodes, edges = torch.randn(30, 16), torch.randn(100, 16)
    edge_index = torch.randint(0, 30, (2, 100))
    concatenated = block.edge_mlp(torch.cat([edges, nodes[edge_index[0]], nodes[edge_index[1]]], dim=1))
    torch.testing.assert_close(block.edge_update(nodes, edges, edge_index, None), concatenated,
                               rtol=1e-5, atol=1e-5)


def test_feature_sizes_follow_the_release_or_the_scene() -> None:
    """The release's defaults: wall distances and a type embedding for every dataset. With
    `wall_features="walls_only"` and `type_embedding="multiple_types"`: no wall features without walls, no
    type embedding with one type. Context only with context."""
    def node_in(config: ModelConfig, meta: Metadata) -> int:
        return LearnedSimulator(config, meta, 0.0).network.node_encoder[0].in_features

    release = ModelConfig(**SMALL)
    assert node_in(release, metadata(walls=True)) == 5 * 2 + 4 + 16
    assert node_in(release, metadata(walls=False, types=1)) == 5 * 2 + 4 + 16
    by_scene = ModelConfig(**SMALL, wall_features="walls_only", type_embedding="multiple_types")
    assert node_in(by_scene, metadata(walls=True)) == 5 * 2 + 4 + 16
    assert node_in(by_scene, metadata(walls=False, types=1)) == 10
    assert node_in(by_scene, metadata(walls=False, types=1, context=1)) == 11
    assert not hasattr(LearnedSimulator(by_scene, metadata(walls=True, types=1), 0.0), "type_embedding")


def test_normalisation_adds_noise_in_quadrature() -> None:
    sim = LearnedSimulator(ModelConfig(**SMALL), metadata(walls=True), 3e-4)
    torch.testing.assert_close(sim.vel_std, torch.tensor([(1e-4 + 9e-8) ** 0.5] * 2))
    torch.testing.assert_close(sim.acc_std, torch.tensor([(1e-6 + 9e-8) ** 0.5] * 2))


ABLATIONS = [
    {"message_passing_steps": 0}, {"message_passing_steps": 1}, {"shared_processor": True},
    {"position_encoding": "absolute"}, {"mlp_hidden_layers": 1}, {"mlp_hidden_layers": 3}, {"latent_size": 16},
    {"self_edges": False}, {"global_latent": True}, {"gravity_bias": True}, {"linear_encoder_decoder": True},
    {"connectivity_radius": 0.1}, {"aggregate": "updated_edges"}, {"init": "torch"},
    {"type_embedding": "multiple_types"}, {"wall_features": "walls_only"},
]


@pytest.mark.parametrize("change", ABLATIONS, ids=lambda c: "-".join(f"{k}={v}" for k, v in c.items()))
def test_every_ablation_switch_builds_and_runs(change: dict) -> None:
    torch.manual_seed(0)
    config = dataclasses.replace(ModelConfig(**SMALL), **change)
    sim = LearnedSimulator(config, metadata(walls=True, context=1, gravity=True), 3e-4)
    w, types = window()
    out = sim(w, types, context=torch.tensor([[0.4]]))
    assert out.shape == (40, 2) and torch.isfinite(out).all()
    out.sum().backward()
    unused = {"network.edge_encoder"} if config.message_passing_steps == 0 else set()
    for name, p in sim.named_parameters():
        if not any(name.startswith(u) for u in unused):
            assert p.grad is not None and torch.isfinite(p.grad).all(), name


def test_unshared_blocks_have_their_own_weights() -> None:
    torch.manual_seed(0)
    unshared = LearnedSimulator(ModelConfig(**SMALL), metadata(walls=True), 0.0)
    shared = LearnedSimulator(dataclasses.replace(ModelConfig(**SMALL), shared_processor=True), metadata(True), 0.0)
    a, b = unshared.network.processor[0], unshared.network.processor[1]
    assert not torch.equal(a.edge_mlp[0].weight, b.edge_mlp[0].weight)
    assert len(shared.network.processor) == 1 and len(unshared.network.processor) == 3
    count = lambda m: sum(p.numel() for p in m.parameters())  # noqa: E731
    assert count(unshared) > count(shared)


def test_gravity_bias_needs_gravity() -> None:
    from gns_bench.config import ConfigError

    with pytest.raises(ConfigError, match="gravity"):
        LearnedSimulator(dataclasses.replace(ModelConfig(**SMALL), gravity_bias=True), metadata(True), 0.0)


def _fixed_block(latent: int, aggregate_messages: bool) -> InteractionNetwork:
    """A block with MLPs of one hidden layer and weights set by formula, not by a random draw."""
    block = InteractionNetwork(latent, 4, 1, global_latent=False, aggregate_messages=aggregate_messages)
    with torch.no_grad():
        for index, parameter in enumerate(block.parameters()):
            values = torch.arange(parameter.numel(), dtype=torch.float32).reshape(parameter.shape)
            parameter.copy_(torch.sin(values * 0.7 + index))
    return block


def _mlp_by_hand(mlp: torch.nn.Sequential, x: torch.Tensor) -> torch.Tensor:
    """Linear, ReLU, Linear, LayerNorm written out."""
    first, second, norm = mlp[0], mlp[2], mlp[3]
    h = torch.relu(x @ first.weight.T + first.bias) @ second.weight.T + second.bias
    h = (h - h.mean(1, keepdim=True)) / torch.sqrt(h.var(1, unbiased=False, keepdim=True) + norm.eps)
    return h * norm.weight + norm.bias


@pytest.mark.parametrize("aggregate_messages", [True, False])
def test_processor_block_matches_both_aggregations_by_hand(aggregate_messages: bool) -> None:
    """A 3-node graph, edges 0->1, 2->1, 1->0, 1->1: the release's block sums the messages m = phi_e(...)
    over incoming edges (graph_nets' InteractionNetwork, residuals added after it); the legacy form sums
    the updated edges e + m. The two differ, and the network computes the one asked for."""
    latent = 3
    nodes = torch.tensor([[0.5, -1.0, 0.2], [2.0, 0.3, -0.4], [-0.7, 1.1, 0.8]])
    edges = torch.tensor([[0.2, 0.4, -0.5], [-1.0, 0.6, 0.3], [0.9, -0.3, 0.0], [0.1, 0.1, 1.2]])
    edge_index = torch.tensor([[0, 2, 1, 1], [1, 1, 0, 1]])
    block = _fixed_block(latent, aggregate_messages)
    senders, receivers = edge_index
    messages = _mlp_by_hand(block.edge_mlp, torch.cat([edges, nodes[senders], nodes[receivers]], dim=1))
    summed_messages = torch.stack([messages[receivers == i].sum(0) for i in range(3)])
    summed_updated = torch.stack([(edges + messages)[receivers == i].sum(0) for i in range(3)])
    by_hand = {True: nodes + _mlp_by_hand(block.node_mlp, torch.cat([nodes, summed_messages], dim=1)),
               False: nodes + _mlp_by_hand(block.node_mlp, torch.cat([nodes, summed_updated], dim=1))}
    with torch.no_grad():
        new_nodes, new_edges, _ = block(nodes, edges, edge_index)
    torch.testing.assert_close(new_edges, edges + messages, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(new_nodes, by_hand[aggregate_messages], rtol=1e-5, atol=1e-5)
    assert (by_hand[True] - by_hand[False]).abs().max() > 0.1  # the test tells the two forms apart


def test_release_initialisation() -> None:
    """Sonnet 1.x's Linear: weights from N(0, 1/fan_in) truncated at 2 std (std 0.88/sqrt(fan_in)), zero
    biases; the type embedding Glorot-uniform. PyTorch's defaults (`init="torch"`) differ measurably."""
    torch.manual_seed(0)
    sim = LearnedSimulator(ModelConfig(connectivity_radius=0.2), metadata(walls=True), 3e-4)  # 128-wide MLPs
    linears = [m for m in sim.modules() if isinstance(m, torch.nn.Linear)]
    assert len(linears) == 3 * (2 + 2 * 10) + 3  # encoders, 10 blocks of two MLPs, decoder
    for layer in linears:
        weight, bound = layer.weight.detach(), 2.0 / layer.in_features**0.5
        assert float(weight.abs().max()) <= bound and torch.all(layer.bias == 0)
        ratio = float(weight.std()) * layer.in_features**0.5
        assert 0.8 < ratio < 0.96, ratio  # 0.880 for a normal truncated at two standard deviations
    table = sim.type_embedding.weight.detach()
    glorot = (6.0 / sum(table.shape)) ** 0.5
    assert float(table.abs().max()) <= glorot and float(table.std()) == pytest.approx(glorot / 3**0.5, rel=0.15)
    torch_sim = LearnedSimulator(ModelConfig(init="torch", connectivity_radius=0.2), metadata(walls=True), 3e-4)
    first = torch_sim.network.processor[0].edge_mlp[0]
    assert float(first.bias.detach().abs().max()) > 0 and float(torch_sim.type_embedding.weight.detach().std()) > 0.8


def test_a_config_saved_before_the_release_switches_rebuilds_the_old_model() -> None:
    """A checkpoint's config written before `aggregate`, `init`, `type_embedding` and `wall_features`
    existed loads with the values its model was trained with, not today's defaults."""
    from gns_bench.config import Config, saved_config

    old = Config().to_dict()
    for key in ("aggregate", "init", "type_embedding", "wall_features"):
        del old["model"][key]
    old["model"]["self_edges"] = False  # written out by every older config
    config = saved_config(old, "old checkpoint")
    assert (config.model.aggregate, config.model.init, config.model.type_embedding, config.model.wall_features) \
        == ("updated_edges", "torch", "multiple_types", "walls_only")
    assert saved_config(Config().to_dict(), "new checkpoint").model == ModelConfig()
    old_sim = LearnedSimulator(dataclasses.replace(config.model, **SMALL), metadata(walls=False, types=1), 0.0)
    assert not hasattr(old_sim, "type_embedding") and old_sim.network.node_encoder[0].in_features == 10
    assert not old_sim.network.processor[0].aggregate_messages


def test_node_and_edge_features_closed_form() -> None:
    """App. B.2: C = 5 velocities normalised by (mean, std); distances to the lower and upper bounds over R,
    clipped to [-1, 1]; edges (p_sender - p_receiver) / R and its norm."""
    from gns_bench.model.features import Normalisation, edge_features, node_features

    radius = 0.1
    bounds = torch.tensor([[0.0, 1.0], [0.0, 2.0]])
    steps = torch.arange(6, dtype=torch.float32)[None, :, None]
    start = torch.tensor([[[0.05, 1.0]], [[0.5, 1.97]], [[0.99, 0.5]]])
    velocity = torch.tensor([[[0.01, 0.0]], [[0.0, 0.002]], [[0.003, 0.004]]])
    window = start + steps * velocity  # [3, 6, 2]: constant velocities
    norm = Normalisation(torch.tensor([0.0, 0.01]), torch.tensor([0.02, 0.04]), torch.zeros(2), torch.ones(2))
    x = node_features(window, norm, bounds=bounds, radius=radius)
    assert x.shape == (3, 5 * 2 + 4)
    expected_velocity = ((velocity[:, 0] - norm.vel_mean) / norm.vel_std).repeat(1, 5)
    torch.testing.assert_close(x[:, :10], expected_velocity)
    last = window[:, -1]
    lower, upper = (last - bounds[:, 0]) / radius, (bounds[:, 1] - last) / radius
    torch.testing.assert_close(x[:, 10:], torch.cat([lower, upper], 1).clamp(-1, 1))
    # by hand for particle 0 at (0.10, 1.00): 1.0 from the left wall (clipped), far from the others
    torch.testing.assert_close(x[0, 10:], torch.tensor([1.0, 1.0, 1.0, 1.0]))
    assert float(x[1, 13]) == pytest.approx(0.2, abs=1e-5)  # at (0.5, 1.98): 0.02 below the top wall, 0.2 R
    assert float(x[2, 12]) == pytest.approx(-0.05, abs=1e-5)  # at (1.005, 0.52): past the right wall, -0.05 R
    # a longer reach (model.wall_range = 3): the same d / R, clipped at 3 R instead
    x3 = node_features(window, norm, bounds=bounds, radius=radius, wall_range=3.0)
    torch.testing.assert_close(x3[:, 10:], torch.cat([lower, upper], 1).clamp(-3, 3))
    torch.testing.assert_close(x3[0, 10:], torch.tensor([1.0, 3.0, 3.0, 3.0]))  # 1 R from the left wall still 1
    edges = torch.tensor([[0, 2], [1, 0]])  # senders, receivers: 0 -> 1 and 2 -> 0
    e = edge_features(last, edges, radius, bounds=bounds)
    displacement = torch.stack([last[0] - last[1], last[2] - last[0]]) / radius
    torch.testing.assert_close(e, torch.cat([displacement, displacement.norm(dim=1, keepdim=True)], 1))


def test_the_simulator_hands_its_wall_range_to_the_features() -> None:
    """model.wall_range reaches the encoder's input: a particle 2 R above the floor sees it at 3 R, not at R."""
    win, types = window()
    win = win.clone()
    win[0] = torch.tensor([0.5, 0.4])  # at rest, 0.4 = 2 R above the floor (R = 0.2)
    features = {}
    for reach in (1.0, 3.0):
        sim = LearnedSimulator(ModelConfig(**SMALL, wall_range=reach), metadata(walls=True), 3e-4)
        features[reach] = sim.graph_inputs(win, types).nodes[0, 10:14]  # after 5 velocities: lower x, y; upper x, y
    torch.testing.assert_close(features[1.0], torch.tensor([1.0, 1.0, 1.0, 1.0]))
    torch.testing.assert_close(features[3.0], torch.tensor([2.5, 2.0, 2.5, 3.0]))


SKIP_VARIANTS = [{}, {"global_latent": True}, {"aggregate": "updated_edges"}, {"shared_processor": True},
                 {"message_passing_steps": 0}, {"gravity_bias": True}]


@pytest.mark.parametrize("change", SKIP_VARIANTS, ids=lambda c: ",".join(c) or "paper")
def test_moving_only_skips_kinematic_work_and_changes_no_prediction(change: dict) -> None:
    """`moving_only`: the decoder, the last node update and the last block's messages into kinematic particles
    are skipped; every predicted particle gets the full forward's acceleration (float64: the same sums in the
    same order, 1e-12), every kinematic one the zero acceleration."""
    torch.manual_seed(0)
    sim = LearnedSimulator(ModelConfig(**{**SMALL, **change}), metadata(walls=True, gravity=True), 3e-4).double()
    w, types = window(n=60)
    types = torch.where(torch.arange(60) % 3 == 0, 3, 5)  # a third kinematic, spread through the scene
    w = w.double()
    with torch.no_grad():
        full = sim(w, types)
        skipped = sim(w, types, moving_only=True)
    moving = types != 3
    assert full[moving].abs().mean() > 1e-2
    torch.testing.assert_close(skipped[moving], full[moving], rtol=1e-12, atol=1e-12)
    still = (-sim.acc_mean / sim.acc_std).double()
    assert torch.equal(skipped[~moving], still.expand(int((~moving).sum()), -1))
    assert not torch.allclose(full[~moving], skipped[~moving])  # the full forward did decode them


def test_a_rollout_with_moving_only_is_the_full_rollout() -> None:
    """Kinematic particles from the data, the rest predicted with and without the skip: float64 rollouts agree
    to 1e-12 over 30 steps; float32 within 1e-6 of the scene's unit (the rounding of smaller products)."""
    from gns_bench.data.format import Trajectory
    from gns_bench.evaluate.rollout import rollout

    torch.manual_seed(1)
    sim = LearnedSimulator(ModelConfig(**SMALL), metadata(walls=True), 3e-4)
    g = torch.Generator().manual_seed(2)
    n, frames = 60, 40
    start = torch.rand(n, 2, generator=g) * 0.5 + 0.25
    velocity = torch.randn(n, 2, generator=g) * 3e-3
    types = torch.where(torch.arange(n) % 3 == 0, 3, 5)
    velocity[types == 3] = 0.0  # static boundary particles
    position = start[None] + torch.arange(frames, dtype=torch.float32)[:, None, None] * velocity[None]
    trajectory = Trajectory(position.numpy(), types.numpy())
    for precision, tolerance in (("fp64", 1e-12), ("fp32", 1e-6)):
        full = rollout(sim, trajectory, precision=precision, moving_only=False).predicted
        skipped = rollout(sim, trajectory, precision=precision, moving_only=True).predicted
        assert full.shape == skipped.shape == (frames - 6, n, 2)
        assert abs(full - skipped).max() <= tolerance, (precision, abs(full - skipped).max())
        assert abs(full[-1] - position[-1].numpy()).max() > 1e-3  # the model's own path, not the data's


@pytest.mark.parametrize("unroll", [0, 2])
def test_training_with_moving_only_has_the_same_loss_and_gradients(unroll: int) -> None:
    """`train.moving_only`: kinematic particles are out of the loss, so skipping their predictions changes
    neither the loss nor a gradient (float64, 1e-12), with and without pushforward unrolling."""
    from gns_bench.data.windows import GraphBatch
    from gns_bench.train.losses import training_loss

    torch.manual_seed(3)
    sim = LearnedSimulator(ModelConfig(**SMALL), metadata(walls=True), 3e-4).double()
    w, _ = window(n=60)
    types = torch.where(torch.arange(60) % 3 == 0, 3, 5)
    w = w.double()
    future = w[:, -1:] + (w[:, -1:] - w[:, -2:-1]) * torch.arange(1, 4, dtype=torch.float64)[None, :, None]
    batch = GraphBatch(w, types, torch.zeros(60, dtype=torch.long), None, future[:, 0], future)
    noise = torch.zeros_like(w)
    results = []
    for moving_only in (False, True):
        sim.zero_grad()
        loss = training_loss(sim, batch, noise, 0.0, unroll=unroll, moving_only=moving_only)
        loss.backward()
        results.append((loss.detach(), [p.grad.clone() for p in sim.parameters()]))
    (full, full_grads), (skipped, skipped_grads) = results
    assert full > 0
    torch.testing.assert_close(skipped, full, rtol=1e-12, atol=0)
    for a, b in zip(full_grads, skipped_grads, strict=True):
        torch.testing.assert_close(b, a, rtol=1e-10, atol=1e-14)
    assert any(g.abs().max() > 0 for g in full_grads)


def boundary_trajectory(n: int = 60, frames: int = 30, context: bool = False):
    """Particles moving above a fixed floor of kinematic ones (a third of them, side by side, so that edges
    join floor particles), optionally with a global context that changes every frame."""
    from gns_bench.data.format import Trajectory

    g = torch.Generator().manual_seed(2)
    floor = torch.arange(n) < n // 3
    start = torch.rand(n, 2, generator=g) * 0.5 + 0.3
    start[floor] = torch.stack([torch.linspace(0.2, 0.8, int(floor.sum())), torch.full((int(floor.sum()),), 0.2)], 1)
    velocity = torch.randn(n, 2, generator=g) * 3e-3
    velocity[floor] = 0.0
    types = torch.where(floor, 3, 5)
    position = start[None] + torch.arange(frames, dtype=torch.float32)[:, None, None] * velocity[None]
    step_context = torch.linspace(0.3, 0.7, frames)[:, None].numpy() if context else None
    return Trajectory(position.numpy(), types.numpy(), step_context), floor


@pytest.mark.parametrize("context", [False, True], ids=["fixed features", "context changing every step"])
def test_a_rollout_reusing_static_encodings_is_the_full_rollout(context: bool,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """The encoder's latents of a fixed floor's particles and of the edges among them, computed once: the
    rollout equals the one that encodes everything every step (float64 to 1e-12, float32 within 1e-6), and
    the latents were indeed reused after the first step, the nodes' only while their features stayed the
    same (a per-step context changes every particle's features, so they are encoded afresh)."""
    from gns_bench.evaluate import rollout as rollout_module
    from gns_bench.model.static_encodings import StaticEncodings

    made: list[StaticEncodings] = []

    class Recorded(StaticEncodings):
        def __init__(self, static: torch.Tensor):
            super().__init__(static)
            made.append(self)

    monkeypatch.setattr(rollout_module, "StaticEncodings", Recorded)
    torch.manual_seed(1)
    sim = LearnedSimulator(ModelConfig(**SMALL), metadata(walls=True, context=1 if context else 0), 3e-4)
    trajectory, floor = boundary_trajectory(context=context)
    steps = trajectory.num_steps - 6
    for precision, tolerance in (("fp64", 1e-12), ("fp32", 1e-6)):
        full = rollout_module.rollout(sim, trajectory, precision=precision, static_encodings=False).predicted
        assert not made
        cached = rollout_module.rollout(sim, trajectory, precision=precision).predicted
        [cache] = made
        assert torch.equal(cache.static, floor)
        assert full.shape == cached.shape == (steps, 60, 2)
        assert abs(full - cached).max() <= tolerance, (precision, abs(full - cached).max())
        assert abs(full[-1] - trajectory.position[-1]).max() > 1e-3  # the model's own path, not the data's
        # edges among floor particles every step after the first; floor nodes only without a changing context
        assert cache.reused == (steps - 1) * (1 if context else 2), cache.reused
        made.clear()


def test_static_encodings_encode_only_what_changed() -> None:
    """After the first call, only moving particles' rows (and edges touching one) reach the encoder; rows
    whose features changed since are encoded again, and the latents are the encoder's own."""
    from gns_bench.model.static_encodings import StaticEncodings

    torch.manual_seed(0)
    linear = torch.nn.Linear(3, 4).double()
    seen: list[int] = []

    def encoder(rows: torch.Tensor) -> torch.Tensor:
        seen.append(rows.shape[0])
        return linear(rows)

    static = torch.tensor([True, True, False, True, False])
    cache = StaticEncodings(static)
    features = torch.randn(5, 3, dtype=torch.float64)
    for _ in range(2):
        torch.testing.assert_close(cache.nodes(features, encoder), linear(features), rtol=0, atol=1e-15)
    assert seen == [5, 2]
    features[4] += 1.0  # a moving particle's features change: still only the moving rows
    features[1] += 1.0  # a static one's change too: all encoded again
    torch.testing.assert_close(cache.nodes(features, encoder), linear(features), rtol=0, atol=1e-15)
    assert seen == [5, 2, 5]
    edge_index = torch.tensor([[0, 1, 2, 3, 4], [1, 0, 0, 1, 3]])  # 0-1 and 1-0 join static particles, 3-1 too
    edges = torch.randn(5, 3, dtype=torch.float64)
    seen.clear()
    for _ in range(2):
        torch.testing.assert_close(cache.edges(edges, edge_index, encoder), linear(edges), rtol=0, atol=1e-15)
    assert seen == [5, 2]
