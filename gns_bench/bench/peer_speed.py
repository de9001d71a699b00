"""A full training iteration of gns-bench and geoelements/gns side by side, timed: the speed half of the peer
comparison (`peer.py` is its tensor-by-tensor half, `peer_budget.py` its training half).

Both codes train the paper's model (Sec. 4 and App. B: M = 10, latent 128, MLPs 2 x 128) on one batch of
synthetic particle clouds (`measure.synthetic_scene`) at two densities: the paper's (one 2,000-particle graph,
about 15 neighbours within R, as the main bench's training step) and that of real training batches (two
1,500-particle graphs at about 28 neighbours, as two frames of a falling-blocks MPM scene make). An iteration is
what each code's training loop does for a step: draw the random-walk noise (Sec. 4.3), run the forward from
positions (neighbour search, features, network), take the masked squared error of normalised accelerations,
backward, Adam. The peer runs in fp32 as its training does, with its own `torch.optim.Adam`; gns-bench runs fp32
and bf16, eager and compiled, as `train.precision` and `train.compile` choose between them, with its fused Adam.
Both build their graphs with gns-bench's neighbour search (`peer.import_geo`: the peer's torch-cluster is not a
dependency here), so the comparison is of everything after the search, which is a few per cent of a step.

The variants are interleaved: each repeat times every variant once, in turn, and a ratio is the median over
repeats of that repeat's ratio, so a host whose speed drifts during the run moves both sides of a ratio alike.

    python -m gns_bench.bench.peer_speed --geo <geoelements/gns checkout> --out reports/bench/<machine>/
"""

from __future__ import annotations

import copy
import importlib
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from gns_bench.bench.measure import NOISE_STD, Scene, batch_of, build_model
from gns_bench.config import ModelConfig
from gns_bench.data.windows import GraphBatch
from gns_bench.model.neighbours import radius_graph
from gns_bench.model.noise import random_walk_position_noise
from gns_bench.train.loop import adam
from gns_bench.train.losses import training_loss

# The targets this comparison is held to: a whole training iteration against the peer's fp32 one.
TARGETS = {"fp32": 3.0, "bf16": 6.0}


@dataclass(frozen=True)
class Density:
    name: str
    graphs: int  # the batch's graphs
    particles: int  # a graph's particles
    neighbours: float  # within R, on average


DENSITIES = (Density("paper density", 1, 2000, 15.0), Density("real training batch", 2, 1500, 28.0))


def ours_iteration(model: ModelConfig, batch: GraphBatch, scene: Scene, precision: str, compiled: bool,
                   seed: int = 0, noise_std: float = NOISE_STD) -> Callable[[], float]:
    """gns-bench's training iteration on `batch` (train/losses.training_loss, the fused Adam of train/loop), on
    a model of its own; returns a function running one iteration and returning its loss."""
    simulator = build_model(model, scene, torch.device("cpu"), seed)
    if compiled:
        simulator.network.compile(dynamic=True)
    optimiser = adam(simulator.parameters(), 1e-4)
    generator = torch.Generator().manual_seed(seed)

    def iteration() -> float:  # every synthetic particle moves: noise on every row
        noise = random_walk_position_noise(tuple(batch.window.shape), noise_std, generator)
        # the target shifted by the last position's noise (correction 0), as the peer's `predict_accelerations`
        loss = training_loss(simulator, batch, noise, 0.0, precision=precision, moving_only=True)
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        return float(loss.detach())

    return iteration


def peer_iteration(geo, model: ModelConfig, batch: GraphBatch, scene: Scene, seed: int = 0,
                   noise_std: float = NOISE_STD) -> Callable[[], float]:
    """geoelements/gns's training iteration on `batch`, as its `train.train` runs one (its noise, its
    `predict_accelerations`, its masked loss, `torch.optim.Adam`), with gns-bench's initial weights copied in.
    `noise_std`: the noise drawn (0 for a check that both codes compute one loss); the normalisation statistics
    are widened by the paper's sigma_v either way, as gns-bench's model's are."""
    from gns_bench.bench.peer import geo_simulator

    noise_utils = importlib.import_module("gns.noise_utils")  # on the path since `import_geo`
    ours = build_model(model, scene, torch.device("cpu"), seed)
    peer = geo_simulator(geo, ours, scene.metadata, NOISE_STD)  # statistics widened by sigma_v as ours are
    optimiser = torch.optim.Adam(peer.parameters(), lr=1e-4)
    counts = torch.bincount(batch.batch)
    torch.manual_seed(seed)

    def iteration() -> float:
        noise = noise_utils.get_random_walk_noise_for_position_sequence(batch.window, noise_std_last_step=noise_std)
        predicted, target = peer.predict_accelerations(next_positions=batch.target, position_sequence_noise=noise,
                                                       position_sequence=batch.window, nparticles_per_example=counts,
                                                       particle_types=batch.particle_type)
        loss = ((predicted - target) ** 2).sum(-1).mean()  # every particle moves: its mask keeps them all
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        return float(loss.detach())

    return iteration


def interleaved(variants: dict[str, Callable[[], object]], repeats: int, warmup: int = 2,
                clock: Callable[[], float] = time.perf_counter) -> dict[str, list[float]]:
    """Seconds of each variant's call, `repeats` times, the variants taking turns within each repeat (after
    `warmup` untimed calls of each, where compilation happens)."""
    for _ in range(warmup):
        for run in variants.values():
            run()
    times: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(repeats):
        for name, run in variants.items():
            start = clock()
            run()
            times[name].append(clock() - start)
    return times


def paired_ratio(baseline: list[float], other: list[float]) -> float:
    """The median over repeats of baseline / other, each repeat's pair timed back to back."""
    return statistics.median(b / o for b, o in zip(baseline, other, strict=True))


VARIANTS = {"ours fp32 eager": ("fp32", False), "ours fp32 compiled": ("fp32", True),
            "ours bf16 eager": ("bf16", False), "ours bf16 compiled": ("bf16", True)}


def measure(geo_source: str | Path, repeats: int = 5, model: ModelConfig | None = None,
            densities: tuple[Density, ...] = DENSITIES) -> list[dict[str, Any]]:
    """One row per density and variant: its median seconds an iteration, the peer's, and the paired ratio."""
    from gns_bench.bench.peer import import_geo

    geo = import_geo(geo_source)
    model = model or ModelConfig()
    rows = []
    for density in densities:
        batch, scene = batch_of(density.graphs, density.particles, density.neighbours)
        variants = {"geoelements/gns fp32": peer_iteration(geo, model, copy.deepcopy(batch), scene)}
        variants |= {name: ours_iteration(model, batch, scene, precision, compiled)
                     for name, (precision, compiled) in VARIANTS.items()}
        times = interleaved(variants, repeats)
        peer = times["geoelements/gns fp32"]
        edges = radius_graph(batch.window[:, -1], scene.metadata.default_connectivity_radius, batch.batch).shape[1]
        for name, seconds in times.items():
            rows.append({"density": density.name, "graphs": density.graphs, "particles": density.particles,
                         "edges": edges, "variant": name, "seconds": statistics.median(seconds),
                         "speed_up": paired_ratio(peer, seconds), "repeats": repeats})
    return rows


def verdicts(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per density and precision, the fastest of gns-bench's variants against the peer's fp32 iteration, held to
    TARGETS (3x in fp32, 6x in bf16)."""
    out = []
    for density in dict.fromkeys(r["density"] for r in rows):
        for precision, target in TARGETS.items():
            ours = [r for r in rows if r["density"] == density and r["variant"].startswith(f"ours {precision}")]
            best = max(ours, key=lambda r: r["speed_up"])
            out.append({"density": density, "precision": precision, "target": target, "variant": best["variant"],
                        "speed_up": best["speed_up"], "met": best["speed_up"] >= target})
    return out


def markdown(rows: list[dict[str, Any]], hardware: str) -> str:
    lines = ["# gns-bench against geoelements/gns: a training iteration", "",
             f"The paper's model, one training iteration (noise, forward from positions, loss, backward, Adam) on "
             f"the same synthetic batch and initial weights; {hardware}. The peer in fp32 as it trains; speed-up: "
             f"the median over {rows[0]['repeats']} interleaved repeats of the peer's time over the variant's in "
             "the same repeat.", "",
             "| batch | variant | particles | edges | s an iteration | speed-up over the peer's fp32 |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['density']} ({r['graphs']} x {r['particles']}) | {r['variant']} | "
                     f"{r['graphs'] * r['particles']} | {r['edges']} | {r['seconds']:.3f} | {r['speed_up']:.2f}x |")
    lines += ["", "| batch | precision | target | fastest of ours | speed-up | met |", "|---|---|---|---|---|---|"]
    for v in verdicts(rows):
        lines.append(f"| {v['density']} | {v['precision']} | >= {v['target']:.0f}x | {v['variant']} | "
                     f"{v['speed_up']:.2f}x | {'yes' if v['met'] else '**no**'} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    from gns_bench.bench.measure import allocated_machine, bench_parser, write_results

    parser = bench_parser(__doc__, repeats=5)
    parser.add_argument("--geo", type=Path, required=True, help="a geoelements/gns checkout (holding gns/)")
    args = parser.parse_args(argv)
    hardware = allocated_machine(args.allocator)
    rows = measure(args.geo, args.repeats)
    write_results(args.out, "peer_speed", markdown(rows, hardware), rows)


if __name__ == "__main__":
    main()
