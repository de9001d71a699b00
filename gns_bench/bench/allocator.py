"""What the allocator setting (`train.allocator`, devices.apply_allocator) does to a training step: the paper's
model's forward, backward and Adam step on a synthetic scene at the density of real training batches, timed in a
fresh process per setting, with the system time and minor page faults each step costs (getrusage). With glibc's
default, the step's large activations are mmapped, handed back to the kernel when freed and faulted in again,
page by page, the next step; kept mapped, they come back from the heap.

    python -m gns_bench.bench.allocator --out reports/bench/<machine>/
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

SETTINGS = ("system", "keep")
WARMUP = 5
PAPER_M = 10  # message-passing steps (Sec. 4, App. C.1)


def allocator_point(setting: str, particles: int, neighbours: float, precision: str, steps: int,
                    warmup: int = WARMUP, message_passing_steps: int = PAPER_M) -> dict[str, Any]:
    """`steps` training steps with the allocator as `setting` says (run in a fresh process: the setting holds for
    the process's life), of the paper's model or one with fewer message-passing steps (the same tensors a
    block, fewer blocks: the tests' quick point)."""
    import resource
    import time

    import torch

    from gns_bench.bench.measure import build_model, synthetic_scene, synthetic_train_step
    from gns_bench.config import ModelConfig
    from gns_bench.devices import apply_allocator
    from gns_bench.train.loop import adam

    used = apply_allocator(setting)
    scene = synthetic_scene(particles, 2, 0.015, neighbours=neighbours)
    model = build_model(ModelConfig(message_passing_steps=message_passing_steps), scene, torch.device("cpu"))
    edges = model.build_graph(scene.window[:, -1])
    optimiser = adam(model.parameters(), 1e-4)
    for _ in range(warmup):  # warm-up: the heap grows to the step's size (about 4 steps with memory kept)
        synthetic_train_step(model, optimiser, scene.window, scene.particle_type, edges, precision)
    before, started = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    for _ in range(steps):
        synthetic_train_step(model, optimiser, scene.window, scene.particle_type, edges, precision)
    wall = time.perf_counter() - started
    after = resource.getrusage(resource.RUSAGE_SELF)
    return {"setting": setting, "allocator": used, "particles": particles, "edges": int(edges.shape[1]),
            "precision": precision, "steps": steps, "threads": torch.get_num_threads(),
            "message_passing_steps": message_passing_steps,
            "seconds_per_step": wall / steps, "system_seconds_per_step": (after.ru_stime - before.ru_stime) / steps,
            "minor_faults_per_step": (after.ru_minflt - before.ru_minflt) / steps}


def measure_allocator(particles: int = 3000, neighbours: float = 28.0, precisions: tuple[str, ...] = ("fp32", "bf16"),
                      steps: int = 10, warmup: int = WARMUP, message_passing_steps: int = PAPER_M
                      ) -> list[dict[str, Any]]:
    """Both settings, each precision, one fresh process each (GLIBC_TUNABLES cleared so "system" is glibc's own)."""
    rows = []
    env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"} | {"PYTHONWARNINGS": "ignore"}
    for precision in precisions:
        for setting in SETTINGS:
            code = ("import json; from gns_bench.bench.allocator import allocator_point; print(json.dumps("
                    f"allocator_point({setting!r}, {particles}, {neighbours}, {precision!r}, {steps}, {warmup}, "
                    f"{message_passing_steps})))")
            done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
            rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
    return rows


def markdown(rows: list[dict[str, Any]], hardware: str) -> str:
    """The rows side by side, each setting's step against the system default's of the same precision."""
    m = rows[0].get("message_passing_steps", PAPER_M)
    model = (f"the paper's model (M = {PAPER_M}" if m == PAPER_M
             else f"the paper's model with M = {m} (the paper's {PAPER_M}")
    lines = [f"Training step of {model}, latent 128) on {rows[0]['particles']:,} particles, "
             f"{rows[0]['edges']:,} edges (the density of a batch of two 1,500-particle frames), "
             f"{rows[0]['threads']} threads, {hardware}; {rows[0]['steps']} steps after {WARMUP} of warm-up, each "
             "setting in a fresh process.", "",
             "| precision | allocator | s / step | system s / step | minor page faults / step | step vs system |",
             "|---|---|---|---|---|---|"]
    default = {r["precision"]: r for r in rows if r["setting"] == "system"}
    for r in rows:
        base = default.get(r["precision"])
        speedup = f"{base['seconds_per_step'] / r['seconds_per_step']:.2f}x faster" if base else "—"
        lines.append(f"| {r['precision']} | {r['allocator']} | {r['seconds_per_step']:.3f} | "
                     f"{r['system_seconds_per_step']:.3f} | {r['minor_faults_per_step']:,.0f} | {speedup} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    import argparse

    from gns_bench.tracking import hardware_description

    parser = argparse.ArgumentParser(description="the allocator setting's effect on a training step")
    parser.add_argument("--out", type=Path, default=None, help="write allocator.md and allocator.json here")
    parser.add_argument("--particles", type=int, default=3000)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--precision", action="append", choices=("fp32", "bf16"),
                        help="repeatable; default fp32, and bf16 where this machine has a bf16 unit (as the bench)")
    args = parser.parse_args(argv)
    if args.precision:
        precisions, left_out = tuple(args.precision), ""
    else:
        import torch

        from gns_bench.bench.run import machine_precisions

        precisions, left_out = machine_precisions(torch.device("cpu"))
    rows = measure_allocator(args.particles, precisions=precisions, steps=args.steps)
    text = markdown(rows, hardware_description("cpu"))
    if left_out:
        text += f"\n{left_out[0].upper()}{left_out[1:]}.\n"
    print(text)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "allocator.md").write_text("# The allocator setting (`train.allocator`)\n\n" + text)
        (args.out / "allocator.json").write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
