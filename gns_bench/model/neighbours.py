"""Neighbour search: directed edges between every pair of particles closer than the connectivity radius.

One entry point, `radius_graph`, with backends behind it:
  scipy          cKDTree per graph on the CPU (the fastest measured on CPU; the default)
  torch_cluster  torch_cluster.radius_graph, when installed (CPU or CUDA), never capped
  cell_list      a pure-torch cell list that runs wherever torch runs, CUDA included

Every backend only proposes candidate pairs (searching a hair beyond R); one shared exact test in
float64, |x_s - x_r|^2 <= R^2, decides, so all backends return the same edge set, in the same order
(sorted by receiver, then sender). Edges follow PyG's convention: edge_index[0] are senders
(sources), edge_index[1] receivers (targets); messages flow sender -> receiver.
"""

from __future__ import annotations

import itertools

import numpy as np
import torch
from scipy.spatial import cKDTree

BACKENDS = ("scipy", "torch_cluster", "cell_list")
_SEARCH_SLACK = 1.0 + 1e-5  # candidates are searched at R * slack, then filtered exactly at R


def radius_graph(positions: torch.Tensor, radius: float, batch: torch.Tensor | None = None, *,
                 backend: str = "scipy", self_edges: bool = False) -> torch.Tensor:
    """Edges [2, E] (senders, receivers) between particles of the same graph within `radius`.

    positions [N, D]; batch [N] graph index of each particle (graphs never connect to each other).
    """
    if backend not in BACKENDS:
        raise ValueError(f"unknown neighbour backend {backend!r}; expected one of {BACKENDS}")
    if positions.ndim != 2:
        raise ValueError(f"positions must be [N, D], got shape {tuple(positions.shape)}")
    n = positions.shape[0]
    if batch is None:
        batch = torch.zeros(n, dtype=torch.long, device=positions.device)
    search = {"scipy": _scipy_candidates, "torch_cluster": _torch_cluster_candidates,
              "cell_list": _cell_list_candidates}[backend]
    senders, receivers = search(positions.detach(), radius * _SEARCH_SLACK, batch)
    senders, receivers = _exact_filter(positions.detach(), senders, receivers, radius)
    if self_edges:
        return radius_graph_from(senders, receivers, n, positions.device)
    return _sorted(senders, receivers, n)


def _exact_filter(positions: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor,
                  radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    keep = senders != receivers
    senders, receivers = senders[keep], receivers[keep]
    pos = positions.to(torch.float64)
    d2 = (pos.index_select(0, senders) - pos.index_select(0, receivers)).square().sum(dim=1)
    keep = d2 <= float(radius) ** 2
    return senders[keep], receivers[keep]


def _sorted(senders: torch.Tensor, receivers: torch.Tensor, n: int) -> torch.Tensor:
    order = torch.argsort(receivers * n + senders)
    return torch.stack([senders[order], receivers[order]])


def _scipy_candidates(positions: torch.Tensor, radius: float,
                      batch: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    pos = positions.cpu().numpy().astype(np.float64)
    graph = batch.cpu().numpy()
    # Graphs in a batch are contiguous and sorted (as batching builds them); search each separately.
    boundaries = np.flatnonzero(np.diff(graph)) + 1
    starts = np.concatenate([[0], boundaries])
    ends = np.concatenate([boundaries, [len(graph)]])
    if len(np.unique(graph)) != len(starts):
        raise ValueError("batch must be sorted: each graph's particles contiguous")
    pairs = []
    for start, end in zip(starts, ends, strict=True):
        tree = cKDTree(pos[start:end])
        p = tree.query_pairs(radius, output_type="ndarray") + start
        pairs.append(p)
    p = np.concatenate(pairs) if pairs else np.zeros((0, 2), dtype=np.int64)
    i = torch.from_numpy(p[:, 0].astype(np.int64)).to(positions.device)
    j = torch.from_numpy(p[:, 1].astype(np.int64)).to(positions.device)
    return torch.cat([i, j]), torch.cat([j, i])  # query_pairs gives i < j once; edges go both ways


def _torch_cluster_candidates(positions: torch.Tensor, radius: float,
                              batch: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    try:
        import torch_cluster
    except ImportError as exc:
        raise RuntimeError("neighbour backend 'torch_cluster' needs the optional dependency: "
                           "pip install 'gns-bench[cluster]'") from exc
    # max_num_neighbors is a cap in torch_cluster; set it to N so no edge is ever dropped.
    n = positions.shape[0]
    edge_index = torch_cluster.radius_graph(positions, r=radius, batch=batch, loop=False,
                                            max_num_neighbors=max(n, 1))
    return edge_index[0], edge_index[1]


def _cell_list_candidates(positions: torch.Tensor, radius: float,
                          batch: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Bin particles into cells of side R; candidates are the particles of the 3^D surrounding cells."""
    n, dim = positions.shape
    device = positions.device
    if n == 0:
        empty = torch.zeros(0, dtype=torch.long, device=device)
        return empty, empty
    pos = positions.to(torch.float64)
    cell = torch.floor((pos - pos.min(dim=0).values) / radius).long() + 1  # +1: offsets stay >= 0
    extent = cell.max(dim=0).values + 2

    def linear_key(c: torch.Tensor) -> torch.Tensor:
        key = batch.clone()
        for d in range(dim):
            key = key * extent[d] + c[:, d]
        return key

    key = linear_key(cell)
    order = torch.argsort(key)
    sorted_key = key[order]
    senders_all, receivers_all = [], []
    arange = torch.arange(n, device=device)
    for offset in itertools.product((-1, 0, 1), repeat=dim):
        neighbour_key = linear_key(cell + torch.tensor(offset, device=device))
        start = torch.searchsorted(sorted_key, neighbour_key, side="left")
        end = torch.searchsorted(sorted_key, neighbour_key, side="right")
        counts = end - start
        total = int(counts.sum())
        if total == 0:
            continue
        receivers = torch.repeat_interleave(arange, counts)
        first = torch.repeat_interleave(start - (torch.cumsum(counts, 0) - counts), counts)
        senders = order[first + torch.arange(total, device=device)]
        senders_all.append(senders)
        receivers_all.append(receivers)
    if not senders_all:
        empty = torch.zeros(0, dtype=torch.long, device=device)
        return empty, empty
    return torch.cat(senders_all), torch.cat(receivers_all)


class VerletNeighbours:
    """Verlet neighbour lists for rollouts: candidates searched at R + skin are reused until some particle
    has moved more than skin / 2 since they were built (then no pair can have crossed R unseen); every
    step filters them to exactly R, so the edges equal a fresh search's, in the same order.
    """

    def __init__(self, radius: float, skin: float, backend: str = "scipy", self_edges: bool = False):
        if skin <= 0:
            raise ValueError(f"skin must be > 0, got {skin}")
        self.radius, self.skin, self.backend, self.self_edges = radius, skin, backend, self_edges
        self._reference: torch.Tensor | None = None
        self._candidates: torch.Tensor | None = None
        self.rebuilds = 0
        self.calls = 0

    def __call__(self, positions: torch.Tensor, batch: torch.Tensor | None = None) -> torch.Tensor:
        self.calls += 1
        positions = positions.detach()
        stale = (self._reference is None or self._reference.shape != positions.shape
                 or float((positions - self._reference).norm(dim=1).max()) > self.skin / 2)
        if stale:
            self._candidates = radius_graph(positions, self.radius + self.skin, batch, backend=self.backend)
            self._reference = positions.clone()
            self.rebuilds += 1
        senders, receivers = _exact_filter(positions, self._candidates[0], self._candidates[1], self.radius)
        if self.self_edges:
            return radius_graph_from(senders, receivers, positions.shape[0], positions.device)
        return torch.stack([senders, receivers])  # the candidates' order survives filtering


def radius_graph_from(senders: torch.Tensor, receivers: torch.Tensor, n: int, device: torch.device) -> torch.Tensor:
    """Add self-loops to filtered edges and restore the canonical order."""
    loops = torch.arange(n, device=device)
    return _sorted(torch.cat([senders, loops]), torch.cat([receivers, loops]), n)


class StaticAwareNeighbours:
    """Neighbour search that finds the edges among static particles (fixed boundaries and obstacles)
    once per rollout: each step only searches pairs with at least one moving particle. Same edges, same
    order as a fresh search. The saving is in the scipy backend (a k-d tree over the static particles
    is built once); other backends search everything each step.
    """

    def __init__(self, static_position: torch.Tensor, static_mask: torch.Tensor, radius: float,
                 backend: str = "scipy", self_edges: bool = False):
        self.radius, self.backend, self.self_edges = radius, backend, self_edges
        self.static_mask = static_mask
        self.static_index = torch.nonzero(static_mask).flatten()
        self.moving_index = torch.nonzero(~static_mask).flatten()
        self.static_position = static_position.detach()
        static = radius_graph(self.static_position[self.static_index], radius, backend=backend)
        self.static_edges = self.static_index[static]  # [2, E_ss] in global indices, found once
        self._static_tree = cKDTree(self.static_position[self.static_index].cpu().numpy().astype(np.float64))

    def __call__(self, positions: torch.Tensor, batch: torch.Tensor | None = None) -> torch.Tensor:
        if batch is not None and int(batch.max()) > 0:
            raise ValueError("StaticAwareNeighbours handles one graph")
        if self.backend != "scipy":
            return radius_graph(positions, self.radius, backend=self.backend, self_edges=self.self_edges)
        positions = positions.detach()
        moving = self.moving_index
        mm = self.moving_index[radius_graph(positions[moving], self.radius * _SEARCH_SLACK, backend="scipy")]
        tree = cKDTree(positions[moving].cpu().numpy().astype(np.float64))
        pairs = tree.sparse_distance_matrix(self._static_tree, self.radius * _SEARCH_SLACK, output_type="ndarray")
        m = moving[torch.from_numpy(pairs["i"].astype(np.int64)).to(moving.device)]
        s = self.static_index[torch.from_numpy(pairs["j"].astype(np.int64)).to(moving.device)]
        senders = torch.cat([mm[0], m, s])
        receivers = torch.cat([mm[1], s, m])
        senders, receivers = _exact_filter(positions, senders, receivers, self.radius)
        senders = torch.cat([senders, self.static_edges[0]])
        receivers = torch.cat([receivers, self.static_edges[1]])
        if self.self_edges:
            return radius_graph_from(senders, receivers, positions.shape[0], positions.device)
        return _sorted(senders, receivers, positions.shape[0])


def rollout_neighbours(radius: float, backend: str, self_edges: bool, skin: float,
                       first_position: torch.Tensor | None = None, static_mask: torch.Tensor | None = None):
    """The neighbour finder a rollout calls each step (positions [N, D] -> edges [2, E]), or None for a fresh
    `radius_graph` every step: Verlet lists with `skin` > 0; else, where some but not all particles never move
    (`static_mask`, at `first_position`), `StaticAwareNeighbours`. All give a fresh search's edges and order."""
    if skin > 0:
        return VerletNeighbours(radius, skin, backend, self_edges)
    if static_mask is not None and bool(static_mask.any()) and not bool(static_mask.all()):
        return StaticAwareNeighbours(first_position, static_mask, radius, backend, self_edges)
    return None
