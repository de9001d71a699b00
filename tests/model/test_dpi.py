"""DPI-Net (the BOXBATH baseline of Sec. 5.5): the rigid projection, the hierarchy, the simulator."""

from __future__ import annotations

import math

import pytest
import torch

from gns_bench.config import Config, ConfigError
from gns_bench.data.format import Metadata
from gns_bench.model.dpi import (
    DPIConfig,
    DPISimulator,
    PropagationStage,
    build_hierarchy,
    kmeans_labels,
    rigid_bodies,
    rigid_projection,
)

SMALL = dict(nf_relation=32, nf_particle=24, nf_effect=24, roots_per_rigid_body=4)
TINY = dict(nf_relation=16, nf_particle=16, nf_effect=16, roots_per_rigid_body=2)
RIGID, WATER, KINEMATIC = 0, 5, 3


@pytest.fixture(autouse=True)
def one_thread():
    """Tiny models gain nothing from threads, and with another job on the cores they were measured 100x
    slower with two (OpenMP workers waiting on each other)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


RADIUS = 0.15  # the datasets' R, which the registry's builder passes resolved (model.connectivity_radius)


def metadata(dim: int) -> Metadata:
    return Metadata(bounds=[[0.0, 1.0]] * dim, sequence_length=10, default_connectivity_radius=RADIUS, dim=dim, dt=1.0,
                    vel_mean=[0.0] * dim, vel_std=[1e-2] * dim, acc_mean=[0.0] * dim, acc_std=[1e-3] * dim,
                    particle_types={"rigid": RIGID, "water": WATER, "kinematic": KINEMATIC})


def random_rotation(dim: int, g: torch.Generator, count: int | None = None) -> torch.Tensor:
    """A uniformly random proper rotation [D, D], or `count` of them [count, D, D]."""
    q, r = torch.linalg.qr(torch.randn(count or 1, dim, dim, generator=g, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r, dim1=1, dim2=2))[:, None, :]
    q[:, :, 0] *= torch.sign(torch.linalg.det(q))[:, None]
    return q if count else q[0]


def rotation_about_last_axis(dim: int, angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    r = torch.eye(dim, dtype=torch.float64)
    r[:2, :2] = torch.tensor([[c, -s], [s, c]], dtype=torch.float64)
    return r


def lattice(dim: int, edge: int, spacing: float, corner: float) -> torch.Tensor:
    axes = [torch.arange(edge, dtype=torch.float64) * spacing + corner] * dim
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, dim)


def toy_trajectory(dim: int, frames: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """[T, N, D] positions and [N] types: a block turning and drifting, water falling, a few still walls."""
    g = torch.Generator().manual_seed(seed)
    block = lattice(dim, 3, 0.05, 0.25)
    centre = block.mean(dim=0)
    water_start = torch.rand(12 if dim == 3 else 10, dim, generator=g, dtype=torch.float64) * 0.3 + 0.4
    water_velocity = torch.randn(water_start.shape, generator=g, dtype=torch.float64) * 0.01
    gravity = torch.zeros(dim, dtype=torch.float64)
    gravity[1] = -1e-3
    walls = lattice(dim, 2, 0.1, 0.05)[:4]
    drift = torch.full((dim,), 0.008, dtype=torch.float64)
    out = []
    for t in range(frames):
        turned = (block - centre) @ rotation_about_last_axis(dim, 0.04 * t).T + centre + drift * t
        water = water_start + water_velocity * t + 0.5 * gravity * t * t
        out.append(torch.cat([turned, water, walls]))
    types = torch.tensor([RIGID] * len(block) + [WATER] * len(water_start) + [KINEMATIC] * len(walls))
    return torch.stack(out).float(), types


def toy_window(dim: int, seed: int = 0, width: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    trajectory, types = toy_trajectory(dim, width, seed)
    return trajectory.transpose(0, 1).contiguous(), types


def pairwise(x: torch.Tensor) -> torch.Tensor:
    return torch.cdist(x.double(), x.double())


# (a) the projection leaves rigid motions alone and makes anything rigid


@pytest.mark.parametrize("dim", [2, 3])
def test_projection_returns_a_rigid_motion_of_the_rest_shape(dim: int) -> None:
    g = torch.Generator().manual_seed(dim)
    rest = torch.rand(20, dim, generator=g, dtype=torch.float64)
    for _ in range(5):
        moved = rest @ random_rotation(dim, g).T + torch.randn(dim, generator=g, dtype=torch.float64)
        torch.testing.assert_close(rigid_projection(moved.float(), rest.float()), moved.float(), rtol=0, atol=1e-5)


@pytest.mark.parametrize("dim", [2, 3])
def test_projection_makes_any_prediction_rigid_and_proper(dim: int) -> None:
    g = torch.Generator().manual_seed(10 + dim)
    rest = torch.rand(15, dim, generator=g, dtype=torch.float64)
    mirrored = rest.clone()
    mirrored[:, 0] = -mirrored[:, 0]  # the best orthogonal fit is a reflection: the projection must refuse it
    for predicted in [torch.randn(15, dim, generator=g, dtype=torch.float64), rest + 0.1 * torch.randn(
            15, dim, generator=g, dtype=torch.float64), mirrored]:
        projected = rigid_projection(predicted, rest)
        torch.testing.assert_close(pairwise(projected), pairwise(rest), rtol=0, atol=1e-10)
        # orientation kept: the linear map from centred rest to centred projection has det +1
        a = torch.linalg.lstsq(rest - rest.mean(0), projected - projected.mean(0)).solution
        assert torch.linalg.det(a) == pytest.approx(1.0, abs=1e-8)


def test_projection_is_translation_equivariant() -> None:
    g = torch.Generator().manual_seed(3)
    rest, predicted = torch.rand(12, 3, generator=g), torch.rand(12, 3, generator=g)
    shift = torch.tensor([0.3, -0.2, 0.1])
    torch.testing.assert_close(rigid_projection(predicted + shift, rest), rigid_projection(predicted, rest) + shift)


# (b) it is the least-squares best fit


@pytest.mark.parametrize("dim", [2, 3])
def test_projection_is_the_least_squares_best_fit(dim: int) -> None:
    g = torch.Generator().manual_seed(20 + dim)
    rest = torch.rand(16, dim, generator=g, dtype=torch.float64)
    predicted = rest @ random_rotation(dim, g).T + 0.05 * torch.randn(16, dim, generator=g, dtype=torch.float64)
    best = (rigid_projection(predicted, rest) - predicted).square().sum()
    centred = rest - rest.mean(0)
    others = centred @ random_rotation(dim, g, 2000).transpose(1, 2) + predicted.mean(0)  # each its best translation
    assert ((others - predicted).square().sum(dim=(1, 2)) >= best - 1e-12).all()
    # and small perturbations of the optimum do no better either
    optimum = rigid_projection(predicted, rest)
    for angle in (1e-3, -1e-3, 1e-2):
        nudged = (optimum - optimum.mean(0)) @ rotation_about_last_axis(dim, angle).T + optimum.mean(0)
        assert (nudged - predicted).square().sum() > best


# The hierarchy: roots from k-means of the rest shape, their relations


def test_a_cube_gets_eight_roots_of_its_octants_and_all_root_pairs() -> None:
    cube = lattice(3, 4, 0.05, 0.0).float()
    labels = kmeans_labels(cube, 8)
    assert torch.bincount(labels).tolist() == [8] * 8
    for k in range(8):  # each cluster is one octant
        octant = (cube[labels == k] >= 0.075).long()
        assert (octant == octant[0]).all()
    bodies = rigid_bodies(torch.zeros(64, dtype=torch.long))
    h = build_hierarchy(cube, bodies, num_leaves=64, roots_per_body=8)
    assert h.num_roots == 8 and h.leaf_to_root.shape == (2, 64) and h.root_to_leaf.shape == (2, 64)
    assert h.root_to_root.shape == (2, 64)  # 8 x 8 ordered pairs, each root with itself included
    assert set(h.root_to_root.flatten().tolist()) == set(range(64, 72))
    torch.testing.assert_close(h.root_to_leaf, h.leaf_to_root.flip(0))
    one = build_hierarchy(cube, bodies, num_leaves=64, roots_per_body=1)
    assert one.num_roots == 1 and one.root_to_root.tolist() == [[64], [64]]  # one body: one self-relation


def test_graph_relations_follow_the_authors() -> None:
    sim = DPISimulator(DPIConfig(**SMALL), metadata(3), RADIUS)
    window, types = toy_window(3)
    window[types == WATER] -= 0.05  # some water within reach of the block
    graph = sim.graph(window, types, None, None, window[:, 0])
    senders, receivers = graph.leaf_edges
    rigid = types == RIGID
    assert not (rigid[senders] & rigid[receivers]).any()  # inside the body only through the hierarchy
    water_near_block = (torch.cdist(window[rigid, -1], window[types == WATER, -1]) <= sim.radius).sum()
    assert water_near_block > 0
    assert (rigid[senders] & (types[receivers] == WATER)).sum() == water_near_block  # block -> water
    assert (rigid[receivers] & (types[senders] == WATER)).sum() == water_near_block  # water -> block
    water = (types == WATER).nonzero()[:, 0]
    self_loops = senders[senders == receivers]
    assert set(water.tolist()) <= set(self_loops.tolist())  # their ball query finds the particle itself
    assert graph.hierarchy.num_roots == 4


def test_propagation_is_the_relation_propagator_on_the_concatenation() -> None:
    """The stage splits W_R [c_k, e_r, e_s] into per-relation and per-node products: it must equal the
    propagation written as the authors' concatenation, with the same parameters (gradients included)."""
    torch.manual_seed(0)
    stage = PropagationStage(attr_size=4, state_size=6, config=DPIConfig(**SMALL)).double()
    m, e = 30, 120
    attr, state = torch.randn(m, 4, dtype=torch.float64), torch.randn(m, 6, dtype=torch.float64)
    effect = torch.randn(m, SMALL["nf_effect"], dtype=torch.float64, requires_grad=True)
    edges = torch.randint(0, m, (2, e))
    nodes = torch.arange(5, 25)
    edges[1] = nodes[torch.randint(0, nodes.numel(), (e,))]  # every relation into one of the stage's nodes

    def concatenated(effect: torch.Tensor) -> torch.Tensor:
        senders, receivers = edges
        encoded = stage.particle_encoder(torch.cat([attr[nodes], state[nodes]], dim=1))
        relation = stage.relation_encoder(
            torch.cat([attr[receivers], attr[senders], state[receivers], state[senders]], dim=1))
        slot = torch.full((m,), -1, dtype=torch.long)
        slot[nodes] = torch.arange(nodes.numel())
        for _ in range(2):
            relation_effect = torch.relu(stage.relation_propagator(
                torch.cat([relation, effect[receivers], effect[senders]], dim=1)))
            incoming = torch.zeros(nodes.numel(), relation_effect.shape[1], dtype=torch.float64)
            incoming = incoming.index_add(0, slot[receivers], relation_effect)
            updated = torch.relu(stage.particle_propagator(torch.cat([encoded, incoming], dim=1)) + effect[nodes])
            effect = effect.index_copy(0, nodes, updated)
        return effect

    ours, theirs = stage(effect, attr, state, edges, nodes, steps=2), concatenated(effect)
    torch.testing.assert_close(ours, theirs, rtol=1e-12, atol=1e-12)
    assert not torch.equal(ours[nodes], effect[nodes])  # the stage did update its nodes
    grad_ours = torch.autograd.grad(ours.square().sum(), stage.relation_propagator.weight)[0]
    grad_theirs = torch.autograd.grad(theirs.square().sum(), stage.relation_propagator.weight)[0]
    torch.testing.assert_close(grad_ours, grad_theirs, rtol=1e-10, atol=1e-12)


# (c) a forward pass: finite, and the rigid part rigid


@pytest.mark.parametrize("dim, head", [(2, "transform"), (3, "transform"), (3, "velocity")])
def test_forward_pass_predicts_a_rigid_block(dim: int, head: str) -> None:
    torch.manual_seed(0)
    sim = DPISimulator(DPIConfig(**SMALL, rigid_head=head), metadata(dim), RADIUS)
    window, types = toy_window(dim)
    with torch.no_grad():
        next_position = sim.predict_next_position(window, types)
    assert next_position.shape == (len(types), dim) and next_position.dtype == torch.float32
    assert torch.isfinite(next_position).all()
    rigid = types == RIGID
    torch.testing.assert_close(pairwise(next_position[rigid]), pairwise(window[rigid, 0]), rtol=0, atol=2e-6)
    assert (next_position[~rigid] - window[~rigid, -1]).abs().max() > 0  # the water moves
    if head == "transform":  # rigid before the projection too: theirs is rigid by construction
        velocity = sim.denormalise_velocity(sim(window, types).detach())
        moved = window[rigid, -1] + velocity[rigid]
        torch.testing.assert_close(pairwise(moved), pairwise(window[rigid, -1]), rtol=0, atol=2e-6)


def test_several_bodies_each_stay_rigid() -> None:
    torch.manual_seed(1)
    sim = DPISimulator(DPIConfig(**SMALL), metadata(3), RADIUS)
    (w0, t0), (w1, t1) = toy_window(3, seed=0), toy_window(3, seed=1)
    window, types = torch.cat([w0, w1 + 0.02]), torch.cat([t0, t1])
    batch = torch.cat([torch.zeros(len(t0)), torch.ones(len(t1))]).long()
    with torch.no_grad():
        batched = sim.predict_next_position(window, types, batch)
        alone = sim.predict_next_position(w0, t0)
    torch.testing.assert_close(batched[: len(t0)], alone, rtol=0, atol=1e-5)  # graphs do not talk
    # two bodies in one graph, told apart by a body id
    body_id = torch.cat([torch.zeros(len(t0)), torch.ones(len(t1))]).long()
    assert rigid_bodies(types, None, body_id).count == 2
    with torch.no_grad():
        together = sim.predict_next_position(window, types, rigid_body=body_id)
    for part in (slice(0, len(t0)), slice(len(t0), len(types))):
        rigid = types[part] == RIGID
        torch.testing.assert_close(pairwise(together[part][rigid]), pairwise(window[part][rigid, 0]), rtol=0,
                                   atol=2e-6)


def test_bf16_and_precomputed_edges() -> None:
    torch.manual_seed(2)
    sim = DPISimulator(DPIConfig(**SMALL), metadata(3), RADIUS)
    window, types = toy_window(3)
    with torch.no_grad():
        reference = sim.predict_next_position(window, types)
        given = sim.predict_next_position(window, types, edge_index=sim.build_graph(window[:, -1]))
        low = sim.predict_next_position(window, types, precision="bf16")
    torch.testing.assert_close(given, reference)
    assert low.dtype == torch.float32 and torch.isfinite(low).all()
    rigid = types == RIGID
    torch.testing.assert_close(pairwise(low[rigid]), pairwise(window[rigid, 0]), rtol=0, atol=2e-6)
    with pytest.raises(ValueError, match="context"):
        sim.predict_next_position(window, types, context=torch.zeros(1, 1))


# (d) the loss trains


def test_training_loss_decreases() -> None:
    torch.manual_seed(0)
    sim = DPISimulator(DPIConfig(**TINY), metadata(2), RADIUS)
    trajectory, types = toy_trajectory(2, frames=8)
    starts = [0, 3, 5]
    window = torch.cat([trajectory[s:s + 2].transpose(0, 1) for s in starts])
    target = torch.cat([trajectory[s + 2] for s in starts])
    all_types = types.repeat(len(starts))
    batch = torch.arange(len(starts)).repeat_interleave(len(types))
    noise = torch.zeros_like(window)
    optimiser = torch.optim.Adam(sim.parameters(), lr=3e-3)
    losses = []
    for _ in range(50):
        loss = sim.training_loss(window, target, all_types, batch, noise)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(loss.item())
    assert all(math.isfinite(v) for v in losses)
    assert losses[-1] < 0.4 * losses[0], losses[::10]


def test_training_loss_ignores_kinematic_particles() -> None:
    torch.manual_seed(0)
    sim = DPISimulator(DPIConfig(**SMALL), metadata(3), RADIUS)
    window, types = toy_window(3, width=3)
    target = window[:, -1] + 0.01
    noise = torch.zeros_like(window)
    moved = target.clone()
    moved[types == KINEMATIC] += 1.0
    a = sim.training_loss(window, target, types, None, noise)
    b = sim.training_loss(window, moved, types, None, noise)
    torch.testing.assert_close(a, b)


# (e) translation: their features are absolute, so the predicted displacement is not invariant


def test_predicted_displacement_is_not_translation_invariant() -> None:
    torch.manual_seed(0)
    sim = DPISimulator(DPIConfig(**SMALL), metadata(3), RADIUS)
    window, types = toy_window(3)
    shift = torch.tensor([0.1, -0.05, 0.07])
    with torch.no_grad():
        a = sim.predict_next_position(window, types) - window[:, -1]
        b = sim.predict_next_position(window + shift, types) - (window[:, -1] + shift)
        normalised_a, normalised_b = sim(window, types), sim(window + shift, types)
    # the graph is the same (relative search) but the states hold absolute positions (their models.py)
    torch.testing.assert_close(sim.build_graph(window[:, -1]), sim.build_graph(window[:, -1] + shift))
    assert (normalised_a - normalised_b).abs().max() > 1e-3  # float error: ~1e-6
    assert (a - b).abs().max() > 1e-5  # displacements ~1e-2 (float error ~1e-7)


# configuration


def test_defaults_are_the_authors_boxbath_settings() -> None:
    c = DPIConfig()
    assert (c.pstep, c.root_pstep, c.roots_per_rigid_body, c.n_his) == (2, 2, 8, 0)
    assert (c.nf_relation, c.nf_particle, c.nf_effect) == (300, 200, 200)
    assert Config().train.learning_rate == 1e-4  # their Adam rate; their 2 accumulated samples: batch_size = 2
    sim = DPISimulator(c, metadata(3), RADIUS)
    assert sim.radius == pytest.approx(0.15) and sim.uses_edges and sim.bounds.shape == (3, 2)
    assert (sim.architecture, sim.input_sequence_length, sim.neighbour_backend, sim.self_edges) == (
        "dpi", 6, "scipy", True)


@pytest.mark.parametrize("bad", [{"dpi.rigid_head": "quaternion"}, {"dpi.pstep": 0}, {"dpi.n_his": 5},
                                 {"dpi.neighbour_backend": "brute"}, {"dpi.radius_scale": 0.0}])
def test_bad_configs_are_refused(bad: dict) -> None:
    from gns_bench.config import load_config

    (key, value), = bad.items()
    with pytest.raises(ConfigError):
        config = load_config(None, [f"{key}={value!r}".replace("'", '"')])
        # n_his beyond the window is caught by the simulator
        DPISimulator(config.dpi, metadata(3), RADIUS)
