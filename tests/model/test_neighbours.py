"""Neighbour backends agree edge for edge with a brute-force search, dense clouds included."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch

from gns_bench.model.neighbours import BACKENDS, radius_graph

AVAILABLE = [b for b in BACKENDS if b != "torch_cluster" or importlib.util.find_spec("torch_cluster")]


def brute_force(pos: np.ndarray, radius: float, batch: np.ndarray) -> set[tuple[int, int]]:
    d2 = ((pos[:, None, :].astype(np.float64) - pos[None, :, :]) ** 2).sum(-1)
    same = batch[:, None] == batch[None, :]
    close = (d2 <= radius**2) & same & ~np.eye(len(pos), dtype=bool)
    senders, receivers = np.nonzero(close)
    return set(zip(senders.tolist(), receivers.tolist(), strict=True))


def as_set(edges: torch.Tensor) -> set[tuple[int, int]]:
    return set(zip(edges[0].tolist(), edges[1].tolist(), strict=True))


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("density", ["sparse", "dense"])
@pytest.mark.parametrize("backend", AVAILABLE)
def test_backends_match_brute_force(backend: str, dim: int, density: str) -> None:
    rng = np.random.default_rng(dim)
    n = 600
    pos = rng.uniform(0, 1, size=(n, dim)).astype(np.float32)
    # dense: a radius giving far more than 32 neighbours per particle (a silent cap would show)
    radius = 0.08 if density == "sparse" else (0.35 if dim == 2 else 0.45)
    batch = np.repeat([0, 1, 2], n // 3)
    expected = brute_force(pos, radius, batch)
    edges = radius_graph(torch.from_numpy(pos), radius, torch.from_numpy(batch), backend=backend)
    assert as_set(edges) == expected
    degree = np.bincount(edges[1].numpy(), minlength=n)
    if density == "dense":
        assert degree.mean() > 32
    # canonical order: sorted by receiver then sender
    key = edges[1] * n + edges[0]
    assert torch.all(key[1:] > key[:-1])


def test_backends_identical_on_lattice_ties() -> None:
    """Particles on a grid whose spacing divides R: pairs sit exactly at distance R."""
    axis = np.arange(12, dtype=np.float32) * 0.025
    pos = np.stack(np.meshgrid(axis, axis), -1).reshape(-1, 2)
    results = [radius_graph(torch.from_numpy(pos), 0.05, backend=b) for b in AVAILABLE]
    for other in results[1:]:
        assert torch.equal(results[0], other)
    assert as_set(results[0]) == brute_force(pos, 0.05, np.zeros(len(pos)))


def test_self_edges_and_bad_backend() -> None:
    pos = torch.rand(20, 2)
    with_loops = radius_graph(pos, 0.2, self_edges=True)
    without = radius_graph(pos, 0.2)
    assert with_loops.shape[1] == without.shape[1] + 20
    with pytest.raises(ValueError, match="unknown neighbour backend"):
        radius_graph(pos, 0.2, backend="kdtree")


@pytest.mark.parametrize("self_edges", [False, True])
def test_verlet_lists_match_a_fresh_search_every_step(self_edges: bool) -> None:
    from gns_bench.model.neighbours import VerletNeighbours

    rng = np.random.default_rng(5)
    pos = rng.uniform(0, 1, size=(800, 2))
    velocity = rng.normal(0, 0.002, size=(800, 2))  # ~R/30 a step, as in the paper's data
    verlet = VerletNeighbours(0.06, skin=0.03, self_edges=self_edges)
    for _ in range(60):
        velocity += rng.normal(0, 0.0002, size=velocity.shape)
        pos = pos + velocity
        positions = torch.tensor(pos, dtype=torch.float32)
        fresh = radius_graph(positions, 0.06, self_edges=self_edges)
        assert torch.equal(verlet(positions), fresh)
    assert 1 < verlet.rebuilds < 30, verlet.rebuilds  # reused most steps, rebuilt when particles moved


def test_static_aware_search_matches_a_fresh_search() -> None:
    from gns_bench.model.neighbours import StaticAwareNeighbours

    rng = np.random.default_rng(6)
    floor = np.stack([np.linspace(0, 1, 200), np.zeros(200)], axis=1)  # a static boundary row
    fluid = rng.uniform([0, 0], [1, 0.3], size=(500, 2))
    pos = np.concatenate([fluid, floor]).astype(np.float32)
    static = torch.zeros(700, dtype=torch.bool)
    static[500:] = True
    search = StaticAwareNeighbours(torch.from_numpy(pos), static, 0.04)
    assert search.static_edges.shape[1] > 0
    for _ in range(5):
        pos[:500] += rng.normal(0, 0.005, size=(500, 2)).astype(np.float32)
        positions = torch.from_numpy(pos)
        assert torch.equal(search(positions), radius_graph(positions, 0.04))
