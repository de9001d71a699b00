"""How many windows one forward of the one-step measurements should take (`evaluate.windows_per_forward`):
the time a window costs when 1, 2, 4, 8 or 16 windows of a scene are batched into one graph, for the paper's
model in fp32 (evaluation's precision) on the synthetic scene at the paper's density, at two particle counts.

    python -m gns_bench.bench.one_step --out reports/bench/<machine>/
"""

from __future__ import annotations

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

WINDOWS = (1, 2, 4, 8, 16)
PARTICLES = (1000, 2000)


@torch.no_grad()
def measure(particles: tuple[int, ...] = PARTICLES, windows: tuple[int, ...] = WINDOWS,
            repeats: int = 3) -> list[dict[str, Any]]:
    rows = []
    for n in particles:
        scene: Scene = synthetic_scene(n, 2)
        model = build_model(ModelConfig(), scene, torch.device("cpu")).eval()
        for k in windows:
            window = scene.window.repeat(k, 1, 1)  # k copies of the scene, one graph each
            types = scene.particle_type.repeat(k)
            batch = torch.arange(k).repeat_interleave(n)
            seconds = timed(lambda m=model, w=window, t=types, b=batch: m.predict_next_position(w, t, b), repeats,
                            warmup=1)
            rows.append({"particles": n, "windows": k, "graph_particles": n * k, "seconds": seconds,
                         "seconds_per_window": seconds / k})
    return rows


def markdown(rows: list[dict[str, Any]], hardware: str) -> str:
    lines = [f"One-step forward (fp32, the paper's model, eval) with several windows batched into one graph: the time "
             f"a window costs, median of repeats; {hardware}.", "",
             "| particles | windows a forward | particles a graph | s a forward | s a window | vs one window |",
             "|---|---|---|---|---|---|"]
    single = {r["particles"]: r["seconds_per_window"] for r in rows if r["windows"] == 1}
    for r in rows:
        lines.append(f"| {r['particles']} | {r['windows']} | {r['graph_particles']} | {r['seconds']:.3f} | "
                     f"{r['seconds_per_window']:.3f} | {r['seconds_per_window'] / single[r['particles']]:.2f}x |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = bench_parser(__doc__, 3)
    args = parser.parse_args(argv)
    machine = allocated_machine(args.allocator)
    rows = measure(repeats=args.repeats)
    text = markdown(rows, machine)
    write_results(args.out, "one_step", text, rows)


if __name__ == "__main__":
    main()
