"""Measurements for `gns-bench bench`: GEMM peak, model FLOPs, training and rollout step times.

All timings are medians of repeated runs after warm-up, taken in one process so that ratios (achieved
FLOP rate / GEMM peak, neighbour-search share of a step, speed-up over a baseline) compare like with like
on a shared machine.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from gns_bench.config import Config, ModelConfig
from gns_bench.data.format import Metadata
from gns_bench.data.windows import GraphBatch
from gns_bench.model import features
from gns_bench.model.neighbours import VerletNeighbours
from gns_bench.model.precision import autocast, compiled_for_inference
from gns_bench.model.simulator import LearnedSimulator
from gns_bench.timing import device_sync as _sync
from gns_bench.timing import skinny_gemm_gflops, timed  # noqa: F401 (the bench's modules import them from here)
from gns_bench.train.checkpoints import build_simulator
from gns_bench.train.loop import adam

GEMM_SECONDS = 1.0  # a size whose product takes longer than this is the last one timed


def gemm_peak_gflops(dtype: torch.dtype, device: torch.device, sizes: tuple[int, ...] = (1024, 2048, 4096),
                     repeats: int = 5) -> float:
    """The best square-GEMM rate over a few sizes, smallest first: the machine's practical matmul limit. Sizes
    stop growing once a product takes `GEMM_SECONDS`: where a dtype has no hardware path (bf16 on a CPU without
    a bf16 unit ran about 1 GFLOP/s on an AMD EPYC family 25 model 1) a 4096 product takes minutes and its
    rate is already known from the smaller ones."""
    best = 0.0
    for n in sorted(sizes):
        a = torch.randn(n, n, device=device).to(dtype)
        b = torch.randn(n, n, device=device).to(dtype)
        seconds = timed(lambda a=a, b=b: a @ b, repeats, sync=_sync(device))
        best = max(best, 2 * n**3 / seconds / 1e9)
        if seconds > GEMM_SECONDS:
            break
    return best


def linear_flops(module: torch.nn.Module, rows: int) -> int:
    return sum(2 * m.in_features * m.out_features * rows for m in module.modules() if isinstance(m, torch.nn.Linear))


def forward_flops(simulator: LearnedSimulator, num_nodes: int, num_edges: int) -> int:
    """Multiply-add FLOPs of one forward pass as implemented (the split first edge layer counted as run)."""
    net = simulator.network
    total = linear_flops(net.node_encoder, num_nodes) + linear_flops(net.decoder, num_nodes)
    if not net.uses_edges:
        return total
    total += linear_flops(net.edge_encoder, num_edges)
    for index in net.schedule:
        block = net.processor[index]
        first = block.edge_mlp[0]
        latent = block.latent_size
        hidden = first.out_features
        total += 2 * latent * hidden * num_edges  # the edge's own part of the first layer
        total += 2 * (2 * latent) * hidden * num_nodes  # sender and receiver projections, per node
        total += linear_flops(block.edge_mlp[1:], num_edges) + linear_flops(block.node_mlp, num_nodes)
    return total


@dataclass
class Scene:
    """A synthetic particle cloud at the paper's density: uniform in a box, ~`neighbours` within R."""

    window: torch.Tensor  # [N, W, D]
    particle_type: torch.Tensor
    metadata: Metadata


def synthetic_scene(num_particles: int, dim: int = 2, radius: float = 0.015, neighbours: float = 15.0,
                    seed: int = 0) -> Scene:
    rng = np.random.default_rng(seed)
    ball = np.pi * radius**2 if dim == 2 else 4 / 3 * np.pi * radius**3
    side = (num_particles * ball / neighbours) ** (1 / dim)  # density giving ~`neighbours` within R
    start = rng.uniform(0.1, 0.1 + side, size=(num_particles, 1, dim))
    velocity = rng.normal(0, 1e-3, size=(num_particles, 1, dim))
    window = start + np.arange(6)[None, :, None] * velocity
    meta = Metadata(bounds=[[0.1, 0.1 + side]] * dim, sequence_length=100, default_connectivity_radius=radius,
                    dim=dim, dt=1.0, vel_mean=[0.0] * dim, vel_std=[1e-3] * dim, acc_mean=[0.0] * dim,
                    acc_std=[1e-4] * dim, particle_types={"water": 5}, walls=True)
    return Scene(torch.tensor(window, dtype=torch.float32), torch.full((num_particles,), 5), meta)


NOISE_STD = 3e-4  # sigma_v the synthetic batches are trained with: the paper's WATERDROP noise (App. B.1)


def batch_of(graphs: int, particles: int, neighbours: float = 15.0, seed: int = 0) -> tuple[GraphBatch, Scene]:
    """`graphs` synthetic clouds of `particles` (`synthetic_scene`, seeds `seed`, `seed + 1`, ...) as one batch of
    disjoint graphs, each particle's target its last velocity carried on plus a small random acceleration; and
    the first cloud's scene (its metadata: bounds, statistics, R)."""
    scenes = [synthetic_scene(particles, neighbours=neighbours, seed=seed + g) for g in range(graphs)]
    window = torch.cat([s.window for s in scenes])
    generator = torch.Generator().manual_seed(seed)
    target = 2 * window[:, -1] - window[:, -2] + 1e-4 * torch.randn(window[:, -1].shape, generator=generator)
    types = torch.cat([s.particle_type for s in scenes])
    graph = torch.repeat_interleave(torch.arange(graphs), particles)
    return GraphBatch(window, types, graph, None, target), scenes[0]


@dataclass
class RolloutBreakdown:
    neighbour_search_s: float
    features_s: float
    gnn_s: float
    integration_s: float
    num_edges: int
    verlet_search_s: float = 0.0  # amortised search time a step with Verlet lists (skin R/2) over 20 steps

    @property
    def total_s(self) -> float:
        return self.neighbour_search_s + self.features_s + self.gnn_s + self.integration_s


@torch.no_grad()
def rollout_breakdown(simulator: LearnedSimulator, scene: Scene, device: torch.device, precision: str = "fp32",
                      repeats: int = 5, compiled: bool = False) -> RolloutBreakdown:
    """One rollout step split into neighbour search, feature building, GNN and integration. `compiled`: the
    network as `eval.compile` runs it (`compiled_for_inference`; its compiling is not timed). Time compiled
    variants after the eager ones: on an AMD EPYC an eager forward pass ran ~40% slower in a process that had
    compiled one (60 against 84 ms)."""
    window = scene.window.to(device)
    types = scene.particle_type.to(device)
    sync = _sync(device)
    edges = simulator.build_graph(window[:, -1])
    search = timed(lambda: simulator.build_graph(window[:, -1]), repeats, sync=sync)

    def build() -> tuple[torch.Tensor, torch.Tensor]:
        inputs = simulator.graph_inputs(window, types, edge_index=edges)
        return inputs.nodes, inputs.edges

    feature_time = timed(build, repeats, sync=sync)
    x, e = build()
    network = compiled_for_inference(simulator).network if compiled else simulator.network
    with autocast(device, precision):
        gnn = timed(lambda: network(x, e, edges), repeats, sync=sync)
        out = network(x, e, edges).float()
    integrate = timed(lambda: features.integrate(window, simulator.denormalise_acceleration(out)), repeats,
                      sync=sync)
    return RolloutBreakdown(search, feature_time, gnn, integrate, int(edges.shape[1]),
                            verlet_search_seconds(simulator, window))


def verlet_search_seconds(simulator: LearnedSimulator, window: torch.Tensor, steps: int = 20) -> float:
    """Search time a step with Verlet lists while the scene drifts at its own velocities."""
    verlet = VerletNeighbours(simulator.radius, simulator.radius / 2, simulator.config.neighbour_backend)
    velocity = window[:, -1] - window[:, -2]
    start = time.perf_counter()
    for step in range(steps):
        verlet(window[:, -1] + step * velocity)
    return (time.perf_counter() - start) / steps


def train_step_seconds(simulator: LearnedSimulator, scene: Scene, device: torch.device, precision: str = "fp32",
                       repeats: int = 5, compile_network: bool = False) -> tuple[float, float]:
    """(seconds per forward+backward+Adam step on a fixed graph, the loss of the last step).
    `compile_network`: torch.compile the network as `train.compile` does; the compilation happens in the
    untimed warm-up steps."""
    if compile_network:
        simulator.network.compile(dynamic=True)
    window = scene.window.to(device)
    types = scene.particle_type.to(device)
    edges = simulator.build_graph(window[:, -1])
    optimiser = adam(simulator.parameters(), 1e-4)
    losses = []

    def step() -> None:
        losses.append(float(synthetic_train_step(simulator, optimiser, window, types, edges, precision)))

    seconds = timed(step, repeats, sync=_sync(device))
    return seconds, losses[-1]


def synthetic_train_step(simulator: LearnedSimulator, optimiser: torch.optim.Optimizer, window: torch.Tensor,
                         types: torch.Tensor, edges: torch.Tensor, precision: str) -> torch.Tensor:
    """One forward+backward+Adam step on a fixed graph, towards zero (normalised) acceleration: the bench's
    training step, timed here and probed by `train.precision/compile = auto` (bench/run.py). Its loss."""
    with autocast(window.device, precision):
        predicted = simulator(window, types, edge_index=edges)
    loss = predicted.float().square().sum(-1).mean()
    optimiser.zero_grad(set_to_none=True)
    loss.backward()
    optimiser.step()
    return loss.detach()


def build_model(config: ModelConfig, scene: Scene, device: torch.device, seed: int = 0) -> LearnedSimulator:
    torch.manual_seed(seed)
    return build_simulator(Config(model=config), scene.metadata).to(device)  # the paper's sigma_v, the scene's R


def bench_parser(doc: str, repeats: int) -> argparse.ArgumentParser:
    """The arguments every stand-alone bench takes (`python -m gns_bench.bench.<name>`): `--out` (its folder),
    `--repeats`, `--allocator` (train.allocator's setting, applied as training runs apply it); its description is
    the first paragraph of the bench's docstring `doc`."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--repeats", type=int, default=repeats)
    parser.add_argument("--allocator", default="auto", help="train.allocator's setting, as training runs apply it")
    return parser


def write_results(out: Path, name: str, text: str, rows: Any, **more: Any) -> None:
    """A stand-alone bench's output: `<out>/<name>.md` (its tables), `<out>/<name>.json` (its rows) and a JSON
    file for each of `more` (`static_encodings=rows`: `static_encodings.json`); the tables printed too."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.md").write_text(text)
    for file, data in {name: rows, **more}.items():
        (out / f"{file}.json").write_text(json.dumps(data, indent=1) + "\n")
    print(text)


def allocated_machine(allocator: str) -> str:
    """Apply `train.allocator`'s setting `allocator` as training runs do, and name the machine with it (a
    table caption of the stand-alone benches: `python -m gns_bench.bench.skips`, `.one_step`)."""
    from gns_bench.devices import apply_allocator, cpu_generation
    from gns_bench.tracking import hardware_description, with_generation

    machine = with_generation(hardware_description("cpu"), "cpu", cpu_generation())
    return f"{machine}; allocator: {apply_allocator(allocator)}"
