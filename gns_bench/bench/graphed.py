"""Training throughput on a GPU against batch size: eager steps against steps replayed from CUDA graphs over
padded buckets (gns_bench/train/padded.py), in graphs a second.

The paper trains on batches of 2 (App. B.1); a GPU that a 2-graph step leaves launch-bound (9-22% of its GEMM
rate on an H200, reports/bench/cuda-nvidia-h200) may train more graphs a second at larger batches, at the
learning rate scaled with them, or with each step's launches replayed as one graph. Each row: the paper's
model on a batch of `batch` synthetic 2,000-particle clouds at the paper's density (`measure.synthetic_scene`),
a step being the neighbour search on the noisy positions, the forward, the loss, backward and Adam; the eager
step with the fused Adam the training loop uses, the graphed one with the capturable Adam it needs, the
neighbour search and the padding outside the graph in both counts.

    python -m gns_bench.bench.graphed --out reports/bench/<gpu>/      (part of `python -m gns_bench.bench.device`)
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from typing import Any

import torch

from gns_bench.bench.measure import NOISE_STD, Scene, batch_of, build_model
from gns_bench.config import ModelConfig
from gns_bench.data.windows import GraphBatch
from gns_bench.model.noise import random_walk_position_noise
from gns_bench.train.loop import adam
from gns_bench.train.losses import training_loss
from gns_bench.train.padded import GraphedSteps, capturable_adam, pad_batch


def steppers(batch: GraphBatch, scene: Scene, model: ModelConfig, precision: str
             ) -> dict[str, Callable[[], torch.Tensor]]:
    """The eager step and the graphed one on `batch` (on the GPU), each on a model of its own from the same
    initial weights, each drawing its own noise every step; both return the step's loss."""
    device = batch.window.device
    generator = torch.Generator().manual_seed(0)

    def noise() -> torch.Tensor:  # every synthetic particle moves: noise on every row
        return random_walk_position_noise(tuple(batch.window.shape), NOISE_STD, generator, device=device)

    eager = build_model(model, scene, device)
    eager_adam = adam(eager.parameters(), 1e-4)

    def eager_step() -> torch.Tensor:
        loss = training_loss(eager, batch, noise(), 0.0, precision=precision)
        eager_adam.zero_grad(set_to_none=True)
        loss.backward()
        eager_adam.step()
        return loss

    graphed = build_model(model, scene, device)
    steps = GraphedSteps(graphed, capturable_adam(graphed.parameters(), 1e-4), precision)

    def graphed_step() -> torch.Tensor:
        return steps.step(pad_batch(graphed, batch, noise(), 0.0))

    return {"eager": eager_step, "CUDA graph, padded": graphed_step}


def measure_graphed(batch_sizes: tuple[int, ...] = (2, 4, 8, 16), particles: int = 2000, repeats: int = 30,
                    precision: str = "fp32", model: ModelConfig | None = None) -> list[dict[str, Any]]:
    """One row per batch size and way of stepping: seconds a step (median of `repeats`, after warm-up and
    capture) and graphs a second."""
    rows = []
    for size in batch_sizes:
        batch, scene = batch_of(size, particles, neighbours=15.0)
        for name, step in steppers(batch.to(torch.device("cuda")), scene, model or ModelConfig(), precision).items():
            for _ in range(3):
                step()
            times = []
            for _ in range(repeats):
                torch.cuda.synchronize()
                began = time.perf_counter()
                float(step())  # the loss read back, as the training loop reads it every step
                times.append(time.perf_counter() - began)
            seconds = statistics.median(times)
            rows.append({"batch": size, "particles": size * particles, "stepping": name, "precision": precision,
                         "seconds": seconds, "graphs_per_second": size / seconds})
    return rows


def markdown(rows: list[dict[str, Any]], hardware: str) -> str:
    eager = {(r["batch"], r["precision"]): r["seconds"] for r in rows if r["stepping"] == "eager"}
    lines = ["# Training throughput against batch size, eager and CUDA graphs", "",
             f"The paper's model on batches of 2,000-particle synthetic clouds at the paper's density; {hardware}. "
             "A step includes the neighbour search and, for the graphed step, padding into its bucket.", "",
             "| batch | precision | stepping | s a step | graphs / s | speed-up over eager |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['batch']} | {r['precision']} | {r['stepping']} | {r['seconds']:.4f} | "
                     f"{r['graphs_per_second']:.1f} | {eager[(r['batch'], r['precision'])] / r['seconds']:.2f}x |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    from gns_bench.bench.measure import bench_parser, write_results
    from gns_bench.tracking import hardware_description

    parser = bench_parser(__doc__, repeats=30)
    args = parser.parse_args(argv)
    rows = [row for precision in ("fp32", "bf16") for row in measure_graphed(repeats=args.repeats,
                                                                             precision=precision)]
    write_results(args.out, "graphed", markdown(rows, hardware_description("cuda")), rows)


if __name__ == "__main__":
    main()
