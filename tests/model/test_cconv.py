"""CConv baseline: the convolution against a brute-force evaluation of its definition, the ball-to-cube map,
invariance, the unrolled loss, and kinematic particles as sources only."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from gns_bench.data.format import Metadata
from gns_bench.model.cconv import (
    CConvConfig,
    CConvSimulator,
    ball_to_cube,
    cconv_geometry,
    continuous_conv,
    learning_rate,
    poly6_window,
)
from gns_bench.model.noise import random_walk_position_noise

KINEMATIC = 3
WATER = 5


# ----------------------------------------------------------------------------------------------
# Brute force: Open3D's reference definition (python/test/ml_ops/cconv_python.py), one pair at a time
# ----------------------------------------------------------------------------------------------

def _disk_to_square(x: float, y: float) -> tuple[float, float]:
    """The four wedges of the inverse concentric map, written out."""
    r = math.hypot(x, y)
    if r == 0.0:
        return 0.0, 0.0
    if abs(y) <= x:  # right wedge
        return r, 4 / math.pi * r * math.atan(y / x)
    if abs(y) <= -x:  # left wedge
        return -r, -4 / math.pi * r * math.atan(y / x)
    if abs(x) <= y:  # top wedge
        return 4 / math.pi * r * math.atan(x / y), r
    return -4 / math.pi * r * math.atan(x / y), -r  # bottom wedge


def _ball_to_cube(p: np.ndarray) -> np.ndarray:
    if len(p) == 2:
        return np.array(_disk_to_square(*p))
    x, y, z = p
    t = float(np.linalg.norm(p))
    if t == 0.0:
        return np.zeros(3)
    if 5 / 4 * z * z > x * x + y * y:  # the caps of the cylinder
        s = math.sqrt(3 * t / (t + abs(z)))
        x, y, z = s * x, s * y, math.copysign(t, z)
    else:  # its side
        s = t / math.hypot(x, y)
        x, y, z = s * x, s * y, 1.5 * z
    return np.array([*_disk_to_square(x, y), z])


def _filter_value(kernel: np.ndarray, g: np.ndarray) -> np.ndarray:
    """(Bi/tri)linear interpolation with clamping of the filter at grid coordinate g (x first); the kernel is
    indexed [(z,) y, x]."""
    k = kernel.shape[0]
    lo = np.clip(np.floor(g).astype(int), 0, k - 1)
    hi = np.clip(lo + 1, 0, k - 1)
    a = np.clip(g - lo, 0, 1)
    value = 0.0
    for corner in itertools.product((0, 1), repeat=len(g)):
        idx = [hi[d] if bit else lo[d] for d, bit in enumerate(corner)]
        w = np.prod([a[d] if bit else 1 - a[d] for d, bit in enumerate(corner)])
        value = value + w * kernel[tuple(reversed(idx))]
    return value


def brute_force_cconv(features, sources, queries, radius, kernel, bias, same_set):
    k = kernel.shape[0]
    out = np.zeros((len(queries), kernel.shape[-1]))
    for i, x in enumerate(queries):
        for j, xj in enumerate(sources):
            rel = (xj - x) / radius
            q2 = float(rel @ rel)
            if q2 > 1 or (same_set and i == j):
                continue
            window = min(max((1 - q2) ** 3, 0.0), 1.0)
            g = (_ball_to_cube(rel) + 1) / 2 * (k - 1)
            out[i] += window * features[j] @ _filter_value(kernel, g)
    return out + bias


def _edges(sources: torch.Tensor, queries: torch.Tensor, radius: float, same_set: bool) -> torch.Tensor:
    d2 = ((queries[:, None] - sources[None]) ** 2).sum(-1)
    near = d2 <= radius**2
    if same_set:
        near.fill_diagonal_(False)
    receivers, senders = torch.nonzero(near, as_tuple=True)
    return torch.stack([senders, receivers])


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("same_set", [True, False])
def test_convolution_equals_brute_force(dim: int, same_set: bool) -> None:
    g = torch.Generator().manual_seed(dim)
    sources = torch.rand(30, dim, generator=g, dtype=torch.float64)
    queries = sources if same_set else torch.rand(25, dim, generator=g, dtype=torch.float64)
    features = torch.randn(30, 3, generator=g, dtype=torch.float64)
    kernel = torch.randn(*[4] * dim, 3, 5, generator=g, dtype=torch.float64)
    bias = torch.randn(5, generator=g, dtype=torch.float64)
    radius = 0.45
    edges = _edges(sources, queries, radius, same_set)
    assert edges.shape[1] > 100  # plenty of pairs, at every distance
    out = continuous_conv(features, sources, queries, edges, radius, kernel, bias)
    expected = brute_force_cconv(features.numpy(), sources.numpy(), queries.numpy(), radius, kernel.numpy(),
                                 bias.numpy(), same_set)
    np.testing.assert_allclose(out.numpy(), expected, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("dim", [2, 3])
def test_gradients_with_respect_to_features_and_filter(dim: int) -> None:
    """The sparse lookup's hand-written backward (its stored transpose) against finite differences, and no
    gradient into the positions (Open3D's op has none)."""
    g = torch.Generator().manual_seed(20 + dim)
    sources = torch.rand(20, dim, generator=g, dtype=torch.float64, requires_grad=True)
    queries = torch.rand(15, dim, generator=g, dtype=torch.float64)
    features = torch.randn(20, 3, generator=g, dtype=torch.float64, requires_grad=True)
    kernel = torch.randn(*[4] * dim, 3, 2, generator=g, dtype=torch.float64, requires_grad=True)
    edges = _edges(sources.detach(), queries, 0.5, same_set=False)
    assert edges.shape[1] > 40

    def conv(f: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
        return continuous_conv(f, sources, queries, edges, 0.5, k)

    assert torch.autograd.gradcheck(conv, (features, kernel))
    conv(features, kernel).sum().backward()
    assert sources.grad is None


def test_queries_without_neighbours_get_the_bias() -> None:
    """An empty edge set (a scene without obstacle particles) is a zero convolution, not an error."""
    pos = torch.rand(7, 2)
    bias = torch.randn(4)
    out = continuous_conv(torch.randn(0, 1), torch.zeros(0, 2), pos, torch.zeros(2, 0, dtype=torch.long), 0.3,
                          torch.randn(4, 4, 1, 4), bias)
    torch.testing.assert_close(out, bias.expand(7, 4))


@pytest.mark.parametrize("dim", [2, 3])
def test_constant_filter_is_a_windowed_neighbour_sum(dim: int) -> None:
    g = torch.Generator().manual_seed(10 + dim)
    pos = torch.rand(30, dim, generator=g)
    features = torch.randn(30, 4, generator=g)
    matrix = torch.randn(4, 6, generator=g)
    kernel = matrix.expand(*[4] * dim, 4, 6).contiguous()
    radius = 0.4
    edges = _edges(pos, pos, radius, same_set=True)
    out = continuous_conv(features, pos, pos, edges, radius, kernel)
    q2 = ((pos[edges[0]] - pos[edges[1]]) ** 2).sum(1) / radius**2
    summed = torch.zeros(30, 4).index_add(0, edges[1], poly6_window(q2)[:, None] * features[edges[0]])
    torch.testing.assert_close(out, summed @ matrix, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("dim", [2, 3])
def test_ball_to_cube_preserves_volume_and_boundary(dim: int) -> None:
    g = torch.Generator().manual_seed(dim)
    p = torch.rand(400_000, dim, generator=g, dtype=torch.float64) * 2 - 1
    p = p[p.norm(dim=1) <= 1]  # uniform in the ball
    u = ball_to_cube(p)
    assert u.abs().max() <= 1 + 1e-12
    # uniform in the cube: every cell of a 4^D grid gets its share
    cell = ((u + 1) / 2 * 4).floor().clamp(0, 3).long()
    flat = sum(cell[:, d] * 4**d for d in range(dim))
    share = torch.bincount(flat, minlength=4**dim).double() / len(p)
    assert (share * 4**dim - 1).abs().max() < 0.05
    # the sphere lands on the cube's surface, the centre on the centre
    sphere = p / p.norm(dim=1, keepdim=True)
    torch.testing.assert_close(ball_to_cube(sphere).abs().amax(dim=1), torch.ones(len(p), dtype=torch.float64))
    assert ball_to_cube(torch.zeros(1, dim)).abs().max() == 0


def test_geometry_weights_are_window_times_partition_of_unity() -> None:
    g = torch.Generator().manual_seed(0)
    pos = torch.rand(30, 3, generator=g)
    edges = _edges(pos, pos, 0.5, same_set=True)
    geometry = cconv_geometry(pos, pos, edges[0], edges[1], 0.5)
    torch.testing.assert_close(geometry.weights.sum(1), geometry.window)
    assert geometry.nodes.min() >= 0 and geometry.nodes.max() < 64


# ----------------------------------------------------------------------------------------------
# The simulator
# ----------------------------------------------------------------------------------------------

GRAVITY = [0.0, -1e-3]


RADIUS = 0.1  # the datasets' R, which the registry's builder passes resolved (model.connectivity_radius)


def metadata(walls: bool = False, dim: int = 2) -> Metadata:
    return Metadata(bounds=[[0.0, 1.0]] * dim, sequence_length=10, default_connectivity_radius=RADIUS, dim=dim, dt=1.0,
                    vel_mean=[0.0] * dim, vel_std=[1e-2] * dim, acc_mean=[0.0] * dim, acc_std=[1e-3] * dim,
                    particle_types={"water": WATER, "kinematic": KINEMATIC}, walls=walls,
                    gravity=(GRAVITY + [0.0])[:dim] if dim == 3 else GRAVITY)


def scene(n_fluid: int = 24, n_kinematic: int = 8, frames: int = 4, seed: int = 0) -> tuple[torch.Tensor, ...]:
    """Fluid falling freely (x_{t+1} = 2 x_t - x_{t-1} + g, which the Euler step reproduces exactly) over a
    static row of kinematic particles."""
    g = torch.Generator().manual_seed(seed)
    start = torch.rand(n_fluid, 2, generator=g) * 0.4 + 0.3
    velocity = torch.randn(n_fluid, 2, generator=g) * 3e-3
    t = torch.arange(frames, dtype=torch.float32)[None, :, None]
    fluid = start[:, None] + t * velocity[:, None] + 0.5 * t * (t - 1) * torch.tensor(GRAVITY)
    floor = torch.stack([torch.linspace(0.3, 0.7, n_kinematic), torch.full((n_kinematic,), 0.25)], dim=1)
    window = torch.cat([fluid, floor[:, None].expand(-1, frames, -1)])
    types = torch.tensor([WATER] * n_fluid + [KINEMATIC] * n_kinematic)
    return window, types


def test_config_resolves_dataset_defaults() -> None:
    sim = CConvSimulator(CConvConfig(), metadata(walls=True), RADIUS)
    assert sim.radius == 0.1 and sim.config.radius == 0.1 and sim.config.wall_features is True
    assert sim.config.gravity == GRAVITY and sim.uses_edges and sim.dim == 2
    assert sim.bounds.shape == (2, 2)
    assert [learning_rate(sim.config, s, 50_000) for s in (0, 25_000, 25_001, 45_001)] == [1e-3, 1e-3, 5e-4, 3.125e-5]
    edges = sim.build_graph(scene()[0][:, -1])
    assert edges.shape[0] == 2 and (edges[0] != edges[1]).all()


def test_free_fall_with_zero_network_is_exact() -> None:
    torch.manual_seed(0)
    sim = CConvSimulator(CConvConfig(), metadata(), RADIUS)
    for p in sim.network.parameters():
        p.data.zero_()
    window, types = scene()
    with torch.no_grad():
        pred = sim.predict_next_position(window[:, :3], types)
    torch.testing.assert_close(pred, window[:, 3])  # fluid: exact free fall; the static floor stays put


def test_translation_invariance() -> None:
    torch.manual_seed(0)
    sim = CConvSimulator(CConvConfig(), metadata(walls=True), RADIUS)
    window, types = scene()
    shift = torch.tensor([0.13, -0.07])
    with torch.no_grad():
        a = sim.predict_next_position(window[:, :3], types) - window[:, 2]
        b = sim.predict_next_position(window[:, :3] + shift, types, bounds=sim.bounds + shift[:, None]) - (
            window[:, 2] + shift)
    free_fall = window[:, 2] - window[:, 1] + torch.tensor(GRAVITY)
    assert (a - free_fall)[:24].abs().mean() > 1e-5  # the network does correct the free fall
    torch.testing.assert_close(a, b, rtol=0, atol=2e-6)


def test_unrolled_loss_is_differentiable_and_learns_free_fall() -> None:
    torch.manual_seed(0)
    config = CConvConfig()
    sim = CConvSimulator(config, metadata(), RADIUS)
    window, types = scene(frames=4)  # W = 2 inputs, S = 2 unrolled targets
    optimiser = torch.optim.Adam(sim.parameters(), lr=config.learning_rate, eps=config.adam_eps)
    losses = []
    for _ in range(50):
        optimiser.zero_grad()
        loss = sim.unrolled_loss(window, types)
        loss.backward()
        assert torch.isfinite(loss)
        assert all(torch.isfinite(p.grad).all() for p in sim.parameters() if p.grad is not None)
        optimiser.step()
        losses.append(loss.item())
    assert sim.network.convs[-1].kernel.grad.abs().sum() > 0
    # the floor: every error zero leaves loss_scale * exp(-n/40) * epsilon^(gamma/2) (~0.7)
    assert losses[-1] < 0.5 * losses[0], losses[::10]


def test_training_noise_corrupts_the_inputs_and_moves_the_targets() -> None:
    """The paper swept CConv's training noise (App. D.1): the GNS's random-walk noise on the input frames, the
    targets moved by (1 - position_correction) times the last frame's noise."""
    torch.manual_seed(0)
    sim = CConvSimulator(CConvConfig(), metadata(), RADIUS)  # no walls: nothing is tied to absolute positions
    window, types = scene(n_kinematic=0, frames=5)  # W = 3 inputs, S = 2 unrolled targets
    with torch.no_grad():
        clean = sim.unrolled_loss(window, types)
        torch.testing.assert_close(sim.unrolled_loss(window, types, position_noise=torch.zeros(24, 3, 2)), clean)
        # a constant offset is noise on positions, none on velocities: at 0% correction the targets carry it
        # too, so a translation-invariant model sees the same problem; at 100% it must undo it, and cannot
        offset = torch.tensor([0.01, -0.02]).expand(24, 3, 2)
        torch.testing.assert_close(sim.unrolled_loss(window, types, position_noise=offset), clean, rtol=1e-4,
                                   atol=1e-6)
        assert sim.unrolled_loss(window, types, position_noise=offset, position_correction=1.0) > 2 * clean
        walk = random_walk_position_noise((24, 3, 2), 3e-3, torch.Generator().manual_seed(1))
        assert not torch.isclose(sim.unrolled_loss(window, types, position_noise=walk), clean, rtol=1e-3)
        with pytest.raises(ValueError, match="input frames"):
            sim.unrolled_loss(window, types, position_noise=torch.zeros(24, 5, 2))


def test_kinematic_particles_are_only_obstacle_sources() -> None:
    torch.manual_seed(0)
    sim = CConvSimulator(CConvConfig(), metadata(), RADIUS)
    window, types = scene(frames=5)  # W = 3, S = 2
    fluid = types != KINEMATIC
    with torch.no_grad():
        step = sim.step(window[:, :3], types)
        # n_i counts fluid neighbours only, at x*, for fluid particles only
        star = window[:, 2] + (window[:, 2] - window[:, 1]) + torch.tensor(GRAVITY)
        d = torch.cdist(star[fluid], star[fluid])
        expected = ((d <= sim.radius).sum(1) - 1).float()
        torch.testing.assert_close(step.fluid_neighbours[fluid], expected)
        assert (step.fluid_neighbours[~fluid] == 0).all()
        # the loss never looks at kinematic targets: move their last frame (a target only, never fed back)
        moved = window.clone()
        moved[~fluid, -1] += 0.05
        torch.testing.assert_close(sim.unrolled_loss(moved, types), sim.unrolled_loss(window, types))
        # kinematic particles reach the fluid only through the obstacle convolution ...
        lifted = window.clone()
        lifted[~fluid, :3] += torch.tensor([0.0, 0.3])  # the floor moves up among the fluid
        base = sim.predict_next_position(window[:, :3], types)[fluid]
        assert (sim.predict_next_position(lifted[:, :3], types)[fluid] - base).abs().max() > 1e-6
        sim.network.conv0_obstacle.kernel.zero_()
        sim.network.conv0_obstacle.bias.zero_()
        base = sim.predict_next_position(window[:, :3], types)[fluid]
        torch.testing.assert_close(sim.predict_next_position(lifted[:, :3], types)[fluid], base)
        # ... and a scene without them predicts the same for the fluid when they are out of reach
        far = window.clone()
        far[~fluid] += 10.0
        alone = sim.predict_next_position(window[fluid, :3], types[fluid])
        torch.testing.assert_close(sim.predict_next_position(far[:, :3], types)[fluid], alone)


def test_batch_bf16_and_3d() -> None:
    torch.manual_seed(0)
    sim = CConvSimulator(CConvConfig(), metadata(walls=True), RADIUS)
    window, types = scene(frames=4)
    n = window.shape[0]
    two = torch.cat([window, window + 0.01])
    batch = torch.repeat_interleave(torch.arange(2), n)
    with torch.no_grad():
        single = sim.predict_next_position(window[:, :2], types)
        both = sim.predict_next_position(two[:, :2], torch.cat([types, types]), batch)
        torch.testing.assert_close(both[:n], single)
        loss_one = sim.unrolled_loss(window, types)
        torch.testing.assert_close(sim.unrolled_loss(two, torch.cat([types, types]), batch), loss_one,
                                   rtol=1e-3, atol=1e-3)
        half = sim.predict_next_position(window[:, :2], types, precision="bf16")
        assert half.dtype == torch.float32
        torch.testing.assert_close(half, single, rtol=0, atol=1e-4)
    sim3 = CConvSimulator(CConvConfig(), metadata(walls=True, dim=3), RADIUS)
    assert sim3.network.conv0_fluid.kernel.shape == (4, 4, 4, 1 + 3 + 6, 32)
    pos = torch.rand(40, 1, 3) * 0.3 + 0.35
    w3 = torch.cat([pos, pos + 1e-3, pos + 2e-3, pos + 3e-3 + torch.tensor([0.0, -1e-3, 0.0])], dim=1)
    t3 = torch.where(torch.arange(40) < 32, WATER, KINEMATIC)
    loss = sim3.unrolled_loss(w3, t3)
    loss.backward()
    assert torch.isfinite(loss) and sim3.network.conv0_fluid.kernel.grad.abs().sum() > 0


def test_wall_distances_reach_model_wall_range() -> None:
    """CConv's wall distances are the GNS's (App. B.2), clipped where `model.wall_range` says: a particle 2 R
    above the floor reads a wall 1 R away (no wall nearer) at the release's 1, and 2 R at 3."""
    from gns_bench.config import load_config
    from gns_bench.simulators import build

    fluid = torch.tensor([[0.5, 2 * RADIUS], [0.5, 0.5]])
    window = torch.stack([fluid, fluid], dim=1)  # at rest
    types = torch.full((2,), WATER)
    seen = {}
    for wall_range in (1.0, 3.0):
        config = load_config(None, ["model.architecture=cconv", f"model.connectivity_radius={RADIUS}",
                                    f"model.wall_range={wall_range}"])
        sim = build(config, metadata(walls=True))
        assert sim.wall_range == wall_range

        def capture(fluid_features, *args, _range=wall_range):
            seen[_range] = fluid_features.detach().clone()
            return torch.zeros(fluid_features.shape[0], 2)

        sim.network.forward = capture
        with torch.no_grad():
            sim.predict_next_position(window, types)
    # features: 1, velocity (2), distance to the lower bounds (2), to the upper bounds (2); the floor is lower y
    floor = 1 + 2 + 1
    assert seen[1.0][0, floor].item() == pytest.approx(1.0, abs=1e-4)
    assert seen[3.0][0, floor].item() == pytest.approx(2.0, abs=1e-2)  # at x* = x + g: 2 R less g's step
    assert seen[1.0][1, floor].item() == 1.0 and seen[3.0][1, floor].item() == 3.0  # far from every wall
