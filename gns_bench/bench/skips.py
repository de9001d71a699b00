"""What the rollout's skips save in a step: kinematic particles' work (`eval.moving_only`) and the encoder's
latents of never-moving particles reused (`eval.static_encodings`).

Kinematic particles' work: the paper's model's forward on one graph with every particle decoded, and with only
the predicted (non-kinematic) ones decoded, their last node update and the last block's messages into them
alone (`EncodeProcessDecode`, `outputs`). Scenes: a synthetic 2D scene at the paper's density (about 15
neighbours within R) with a share of its particles kinematic, spread at random (the saving depends only on how
many particles and the edges into them are skipped), and, given `--dataset`, the first frame window of each
named dataset's first test trajectory as it is.

Static encodings: the same forward (moving particles decoded alone, as rollouts run) with every node and edge
encoded, and with a fixed floor's latents (its particles' and the edges among them) taken from the rollout's
first step (`model/static_encodings.py`). Scene: the synthetic one with its lowest share of particles a floor
that does not move, side by side as a boundary is (so most of its edges join floor particles).

Each row: time with and without, their ratio, and the largest difference of a predicted particle's
acceleration (normalised units) between the two.

    python -m gns_bench.bench.skips --out reports/bench/<machine>/ [--dataset data/waterramps-cpu-s0 ...]
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import torch

from gns_bench.bench.measure import (
    Scene,
    allocated_machine,
    bench_parser,
    build_model,
    synthetic_scene,
    timed,
    write_results,
)
from gns_bench.config import ModelConfig
from gns_bench.data.format import KINEMATIC_PARTICLE_TYPE
from gns_bench.model.precision import autocast
from gns_bench.model.static_encodings import StaticEncodings

SHARES = (0.0, 0.25, 0.5)
FLOOR_SHARES = (0.25, 0.5)


def with_kinematic_share(scene: Scene, share: float, seed: int = 0) -> Scene:
    """`scene` with a random `share` of its particles made kinematic."""
    g = torch.Generator().manual_seed(seed)
    kinematic = torch.rand(scene.window.shape[0], generator=g) < share
    types = torch.where(kinematic, KINEMATIC_PARTICLE_TYPE, scene.particle_type)
    metadata = dataclasses.replace(scene.metadata, particle_types={**scene.metadata.particle_types,
                                                                   "kinematic": KINEMATIC_PARTICLE_TYPE})
    return Scene(scene.window, types, metadata)


def with_static_floor(scene: Scene, share: float) -> tuple[Scene, torch.Tensor]:
    """`scene` with its lowest `share` of particles (by height) a kinematic floor at rest through the window,
    and that floor's mask."""
    n, w = scene.window.shape[:2]
    floor = torch.zeros(n, dtype=torch.bool)
    floor[scene.window[:, -1, 1].argsort()[: int(share * n)]] = True
    window = scene.window.clone()
    window[floor] = window[floor][:, -1:].expand(-1, w, -1)
    types = torch.where(floor, KINEMATIC_PARTICLE_TYPE, scene.particle_type)
    metadata = dataclasses.replace(scene.metadata, particle_types={**scene.metadata.particle_types,
                                                                   "kinematic": KINEMATIC_PARTICLE_TYPE})
    return Scene(window, types, metadata), floor


def dataset_scene(path: Path) -> tuple[str, Scene]:
    """The first input window of `path`'s first test trajectory, as the rollout starts from it."""
    from gns_bench.data.format import load_split, read_metadata

    metadata = read_metadata(path)
    trajectory = load_split(path, "test")[0]
    w = ModelConfig().input_sequence_length
    window = torch.from_numpy(trajectory.position[:w]).transpose(0, 1).contiguous()
    return path.name, Scene(window, torch.from_numpy(trajectory.particle_type), metadata)


@torch.no_grad()
def skip_row(name: str, scene: Scene, precision: str, repeats: int) -> dict[str, Any]:
    device = torch.device("cpu")
    model = build_model(ModelConfig(), scene, device).eval()
    window, types = scene.window, scene.particle_type
    edges = model.build_graph(window[:, -1])

    def forward(moving_only: bool) -> torch.Tensor:
        with autocast(device, precision):
            return model(window, types, edge_index=edges, moving_only=moving_only)

    full, skipped = timed(lambda: forward(False), repeats), timed(lambda: forward(True), repeats)
    moving = types != KINEMATIC_PARTICLE_TYPE
    difference = (forward(False).float() - forward(True).float())[moving].abs().max()
    return {"scene": name, "precision": precision, "particles": int(window.shape[0]),
            "kinematic_share": float((~moving).float().mean()), "edges": int(edges.shape[1]),
            "full_s": full, "moving_only_s": skipped, "speedup": full / skipped,
            "max_difference": float(difference)}


@torch.no_grad()
def encodings_row(name: str, scene: Scene, floor: torch.Tensor, precision: str, repeats: int) -> dict[str, Any]:
    device = torch.device("cpu")
    model = build_model(ModelConfig(), scene, device).eval()
    window, types = scene.window, scene.particle_type
    edges = model.build_graph(window[:, -1])
    cache = StaticEncodings(floor)

    def forward(cached: bool) -> torch.Tensor:
        with autocast(device, precision):
            return model(window, types, edge_index=edges, moving_only=True,
                         static_encodings=cache if cached else None)

    forward(True)  # a rollout's first step fills the cache
    encoded, reused = timed(lambda: forward(False), repeats), timed(lambda: forward(True), repeats)
    moving = ~floor
    difference = (forward(False).float() - forward(True).float())[moving].abs().max()
    among = floor[edges[0]] & floor[edges[1]]
    return {"scene": name, "precision": precision, "particles": int(window.shape[0]),
            "static_share": float(floor.float().mean()), "edges": int(edges.shape[1]),
            "static_edge_share": float(among.float().mean()), "encoded_s": encoded, "reused_s": reused,
            "speedup": encoded / reused, "max_difference": float(difference)}


def measure_encodings(particles: int = 2000, repeats: int = 7, precisions: tuple[str, ...] = ("fp32", "bf16")
                      ) -> list[dict[str, Any]]:
    scenes = [(f"synthetic, {share:.0%} a fixed floor", *with_static_floor(synthetic_scene(particles, 2), share))
              for share in FLOOR_SHARES]
    return [encodings_row(name, scene, floor, precision, repeats) for name, scene, floor in scenes
            for precision in precisions]


def measure(particles: int = 2000, datasets: tuple[Path, ...] = (), repeats: int = 7,
            precisions: tuple[str, ...] = ("fp32", "bf16")) -> list[dict[str, Any]]:
    scenes = [(f"synthetic, {share:.0%} kinematic", with_kinematic_share(synthetic_scene(particles, 2), share))
              for share in SHARES] + [dataset_scene(path) for path in datasets]
    return [skip_row(name, scene, precision, repeats) for name, scene in scenes for precision in precisions]


def markdown(rows: list[dict[str, Any]], hardware: str) -> str:
    lines = [f"Rollout step's forward with every particle decoded against the predicted ones alone "
             f"(`eval.moving_only`), median of repeats; {hardware}.", "",
             "| scene | precision | particles | kinematic | edges | all decoded, ms | moving only, ms | speed-up | "
             "largest difference (normalised acceleration) |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['precision']} | {r['particles']} | {r['kinematic_share']:.0%} | "
                     f"{r['edges']} | {1e3 * r['full_s']:.1f} | {1e3 * r['moving_only_s']:.1f} | "
                     f"{r['speedup']:.2f}x | {r['max_difference']:.1e} |")
    return "\n".join(lines) + "\n"


def encodings_markdown(rows: list[dict[str, Any]], hardware: str) -> str:
    lines = [f"Rollout step's forward (moving particles decoded alone) with every node and edge encoded against a "
             f"fixed floor's latents reused from the first step (`eval.static_encodings`), median of repeats; "
             f"{hardware}.", "",
             "| scene | precision | particles | static | edges | edges within the floor | all encoded, ms | "
             "floor reused, ms | speed-up | largest difference (normalised acceleration) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['precision']} | {r['particles']} | {r['static_share']:.0%} | "
                     f"{r['edges']} | {r['static_edge_share']:.0%} | {1e3 * r['encoded_s']:.1f} | "
                     f"{1e3 * r['reused_s']:.1f} | {r['speedup']:.2f}x | {r['max_difference']:.1e} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = bench_parser(__doc__, 7)
    parser.add_argument("--particles", type=int, default=2000)
    parser.add_argument("--dataset", type=Path, nargs="*", default=[])
    args = parser.parse_args(argv)
    hardware = allocated_machine(args.allocator)
    rows = measure(args.particles, tuple(args.dataset), args.repeats)
    reused = measure_encodings(args.particles, args.repeats)
    text = markdown(rows, hardware) + "\n" + encodings_markdown(reused, hardware)
    write_results(args.out, "skips", text, rows, static_encodings=reused)


if __name__ == "__main__":
    main()
