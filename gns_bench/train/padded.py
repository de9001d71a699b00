"""A training step on graphs padded to fixed sizes, so that a GPU can replay it as one CUDA graph.

A GPU runs the paper's training step (Sec. 4, App. B: M = 10 blocks of MLPs, LayerNorm, scatter-sums) as a few
thousand kernel launches on tensors too small to hide them: on an H200 the 2,000-particle step reached 9-22% of
its GEMM rate (reports/bench/cuda-nvidia-h200). A CUDA graph replays a captured step with one launch, but only
for the shapes it captured, and a batch's node and edge counts change every step. So the counts are rounded up
to a few bucket sizes (`bucket`), each padded batch filled into the buffers of its bucket's graph, as PhysicsNeMo
and fairchem do for the same reason.

Padding is exact for everything the loss reads: the pad particles sit in a graph of their own (batch index
past the last real graph) with edges only among themselves (each pad edge joins the first pad particle to
itself), so no message reaches a real particle from a pad one, and the loss weighs each real moving particle by
1 / (moving particles) and pad ones by 0. Row-wise operations (MLPs, LayerNorm) see the same rows; the GEMMs
over more rows may round a real row differently, which the tests bound. The neighbour search, whose edge count
is data-dependent, stays outside the step. The global-latent ablation (App. C.1) averages over every node and
edge and is refused.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from gns_bench.data.windows import GraphBatch
from gns_bench.model.features import acceleration_from_next_position
from gns_bench.model.noise import noisy_training_pair
from gns_bench.model.precision import autocast
from gns_bench.model.simulator import LearnedSimulator, kinematic_mask

PAD_TYPE = 0  # the pad particles' type: any type the embedding has; they are outside the loss and every real graph


def bucket(size: int, growth: float = 1.25, smallest: int = 256, multiple: int = 64) -> int:
    """The bucket `size` rounds up to: the first of smallest, smallest * growth, smallest * growth^2, ... (each
    rounded up to a multiple of `multiple`) above `size`, so at least one pad row is left. A 25% growth keeps
    the padding under 25% of the work and the number of graphs captured to a few per dataset."""
    if size < 0:
        raise ValueError(f"bucket: a size of at least 0, got {size}")
    edge = smallest
    while edge <= size:
        edge = math.ceil(edge * growth / multiple) * multiple
    return edge


@dataclass
class PaddedBatch:
    """One training step's inputs padded to (nodes, edges): the noisy window, its target, the types, the graph
    index, the edges searched on the noisy last positions, and each row's weight in the loss."""

    window: torch.Tensor  # [nodes, W, D] noisy input positions
    target: torch.Tensor  # [nodes, D] the next positions the noisy window must reach (noise-corrected)
    particle_type: torch.Tensor  # [nodes]
    batch: torch.Tensor  # [nodes] graph index; pad rows in a graph of their own
    edge_index: torch.Tensor  # [2, edges]; pad edges join the first pad row to itself
    weight: torch.Tensor  # [nodes] 1 / (moving particles) on real moving rows, 0 elsewhere

    @property
    def shape(self) -> tuple[int, int]:
        return self.window.shape[0], self.edge_index.shape[1]


def pad_batch(simulator: LearnedSimulator, batch: GraphBatch, position_noise: torch.Tensor,
              position_correction: float, nodes: int | None = None, edges: int | None = None,
              num_moving: int | None = None) -> PaddedBatch:
    """Step inputs as `losses.training_loss` makes them (the noisy window and its target, Sec. 4.3; the edges
    of its last positions), padded to `nodes` and `edges` rows (default: their buckets). `num_moving`: the
    whole batch's moving count where this process holds part of it (as `training_loss` takes it)."""
    if simulator.config.global_latent:
        raise ValueError("model.global_latent: the global block averages over every node and edge, pad rows "
                         "included; padded steps cover the paper's model without it")
    window, target = noisy_training_pair(batch.window, batch.target, position_noise, position_correction)
    edge_index = simulator.build_graph(window[:, -1], batch.batch)
    n, e = window.shape[0], edge_index.shape[1]
    nodes = bucket(n) if nodes is None else nodes
    edges = bucket(e) if edges is None else edges
    if nodes <= n or edges < e:
        raise ValueError(f"pad_batch: {n} particles and {e} edges do not fit {nodes} rows (at least one of "
                         f"them a pad row) and {edges} edges")
    device = window.device
    moving = ~kinematic_mask(batch.particle_type)
    count = int(moving.sum()) if num_moving is None else num_moving
    weight = torch.zeros(nodes, device=device)
    weight[:n] = moving.float() / max(count, 1)
    pad_rows = nodes - n
    pad_window = window[-1:, -1:].expand(pad_rows, window.shape[1], -1)  # at rest on the last real position
    graphs = int(batch.batch[-1]) + 1 if n else 0
    return PaddedBatch(
        window=torch.cat([window, pad_window]),
        target=torch.cat([target, pad_window[:, -1]]),
        particle_type=torch.cat([batch.particle_type,
                                 torch.full((pad_rows,), PAD_TYPE, dtype=batch.particle_type.dtype, device=device)]),
        batch=torch.cat([batch.batch, torch.full((pad_rows,), graphs, dtype=batch.batch.dtype, device=device)]),
        edge_index=torch.cat([edge_index, torch.full((2, edges - e), n, dtype=edge_index.dtype, device=device)], 1),
        weight=weight)


def padded_loss(simulator: LearnedSimulator, padded: PaddedBatch, precision: str = "fp32") -> torch.Tensor:
    """`training_loss` on a padded batch: the squared error of normalised accelerations, summed over
    dimensions, weighted per row (`PaddedBatch.weight`). Nothing here reads a value back to the host or
    depends on the data for a shape, so a CUDA graph can capture it with the backward and the optimiser's
    step."""
    target = simulator.normalise_acceleration(acceleration_from_next_position(padded.window, padded.target))
    with autocast(padded.window.device, precision):
        predicted = simulator(padded.window, padded.particle_type, padded.batch,
                              edge_index=padded.edge_index).float()
    return ((predicted - target).square().sum(dim=-1) * padded.weight).sum()


FIELDS = ("window", "target", "particle_type", "batch", "edge_index", "weight")


def capturable_adam(parameters, lr: float, eps: float = 1e-8) -> torch.optim.Adam:
    """Adam as `loop.adam` makes it, its rate a device tensor and its step capturable, so a captured step reads
    the rate the schedule last wrote (`set_learning_rate`) rather than the one it was captured with."""
    parameters = list(parameters)
    device = parameters[0].device
    return torch.optim.Adam(parameters, lr=torch.tensor(lr, device=device), eps=eps, capturable=True)


def set_learning_rate(optimiser: torch.optim.Optimizer, lr: float) -> None:
    """Write the schedule's rate in place where the optimiser holds it as a tensor (a captured step reads it
    there), else as the float it is."""
    for group in optimiser.param_groups:
        if isinstance(group["lr"], torch.Tensor):
            group["lr"].fill_(lr)
        else:
            group["lr"] = lr


def give_state(optimiser: torch.optim.Optimizer) -> None:
    """Allocate Adam's state before a capture (the step that would allocate it cannot be captured) without a
    training step: a step on zero gradients leaves the weights and both moments at what they were (zero
    moments: the update is 0 / (0 + eps)), and its step count is set back to 0."""
    params = [p for group in optimiser.param_groups for p in group["params"]]
    if all(optimiser.state.get(p) for p in params):
        return
    for p in params:
        p.grad = torch.zeros_like(p)
    optimiser.step()
    for p in params:
        optimiser.state[p]["step"].zero_()
    optimiser.zero_grad(set_to_none=True)


class GraphedSteps:
    """The whole training step (`padded_loss`, its backward, the optimiser's step) captured as one CUDA graph per
    padded shape and replayed for every later batch of that shape (`step`). The optimiser must be capturable
    (`capturable_adam`). Capturing adds no training step: the warm-up before a capture runs forward and
    backward only, and an optimiser without state is given it by a step on zero gradients (which moves no
    weight: Adam's moments stay zero) whose step count is then set back."""

    def __init__(self, simulator: LearnedSimulator, optimiser: torch.optim.Optimizer, precision: str = "fp32",
                 warmup: int = 3):
        if not torch.cuda.is_available():
            raise RuntimeError("GraphedSteps: CUDA graphs need a CUDA device")
        self.simulator, self.optimiser, self.precision, self.warmup = simulator, optimiser, precision, warmup
        self.graphs: dict[tuple[int, int], tuple[PaddedBatch, torch.cuda.CUDAGraph, torch.Tensor]] = {}
        self.pool = torch.cuda.graph_pool_handle()

    def step(self, padded: PaddedBatch) -> torch.Tensor:
        """One training step on `padded`; its loss (a device tensor of its own)."""
        entry = self.graphs.get(padded.shape) or self._capture(padded)
        static, graph, loss = entry
        for field in FIELDS:
            getattr(static, field).copy_(getattr(padded, field))
        graph.replay()
        return loss.detach().clone()  # the pool's loss is overwritten by the next replay

    def _capture(self, padded: PaddedBatch) -> tuple[PaddedBatch, torch.cuda.CUDAGraph, torch.Tensor]:
        static = PaddedBatch(**{field: getattr(padded, field).clone() for field in FIELDS})
        give_state(self.optimiser)
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            for _ in range(self.warmup):
                self.optimiser.zero_grad(set_to_none=True)
                padded_loss(self.simulator, static, self.precision).backward()
        torch.cuda.current_stream().wait_stream(side)
        self.optimiser.zero_grad(set_to_none=True)  # the captured backward allocates the gradients it writes
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph, pool=self.pool):
            loss = padded_loss(self.simulator, static, self.precision)
            loss.backward()
            self.optimiser.step()
        self.graphs[padded.shape] = (static, graph, loss)
        return self.graphs[padded.shape]
