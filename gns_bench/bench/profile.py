"""Where a training step's time goes on this machine: the torch profiler's operators and oneDNN's kernels.

The paper's model, one forward+backward+Adam step on a fixed graph (the bench's training step,
`measure.synthetic_train_step`), on a synthetic scene at the density of real training batches (two 1,500-particle
frames at about 28 neighbours within R), in each precision asked for:

- the torch profiler's operators by self CPU time over the timed steps: the share of the step each takes, so a
  machine's gap shows where it is (matrix products, scatters, LayerNorm, casts, the optimiser);
- oneDNN's verbose log of the same steps, run in a child process (the log is switched on before oneDNN starts):
  the time of each primitive kind and implementation, whose name says the instruction set the kernel used
  (e.g. `brg_matmul:avx512_core_amx` on an Intel Xeon with AMX, `..._avx512_core_bf16` on an AMD EPYC), so a
  bf16 product that fell back to a slower path shows.

    python -m gns_bench.bench.profile --out reports/bench/<machine>/ [--precision fp32 bf16]
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections import defaultdict
from typing import Any

import torch

from gns_bench.bench.measure import (
    allocated_machine,
    bench_parser,
    build_model,
    synthetic_scene,
    synthetic_train_step,
    write_results,
)
from gns_bench.config import ModelConfig
from gns_bench.train.loop import adam

PARTICLES, NEIGHBOURS = 3000, 28.0  # a batch of two 1,500-particle frames of a falling-blocks MPM scene
TOP = 15  # operators and kernels listed


def _step(precision: str, particles: int, neighbours: float):
    """A ready training step (a closure) on the scene, and the graph's edge count."""
    scene = synthetic_scene(particles, 2, neighbours=neighbours)
    model = build_model(ModelConfig(), scene, torch.device("cpu"))
    window, types = scene.window, scene.particle_type
    edges = model.build_graph(window[:, -1])
    optimiser = adam(model.parameters(), 1e-4)
    return (lambda: synthetic_train_step(model, optimiser, window, types, edges, precision)), int(edges.shape[1])


def operators(precision: str, steps: int, particles: int = PARTICLES, neighbours: float = NEIGHBOURS
              ) -> dict[str, Any]:
    """The torch profiler's operators of `steps` training steps (after two untimed), by self CPU time."""
    from torch.profiler import ProfilerActivity, profile

    step, edges = _step(precision, particles, neighbours)
    for _ in range(2):
        step()
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(steps):
            step()
    events = prof.key_averages()
    total = sum(e.self_cpu_time_total for e in events)
    rows = sorted(({"operator": e.key, "calls": e.count // steps, "ms_a_step": e.self_cpu_time_total / steps / 1e3,
                    "share": e.self_cpu_time_total / total} for e in events), key=lambda r: -r["ms_a_step"])
    return {"precision": precision, "particles": particles, "edges": edges, "steps": steps,
            "ms_a_step": total / steps / 1e3, "operators": rows[:TOP]}


def kernels(precision: str, steps: int, particles: int = PARTICLES, neighbours: float = NEIGHBOURS,
            allocator: str = "auto") -> dict[str, Any]:
    """oneDNN's primitives over `steps` training steps, from its verbose log in a child process (with the
    allocator setting applied as in the parent): time by kind and implementation (ISA included), and the share of
    the logged time each takes."""
    code = (f"from gns_bench.devices import apply_allocator; apply_allocator({allocator!r}); "
            f"from gns_bench.bench.profile import _verbose_steps; _verbose_steps({precision!r}, {steps}, "
            f"{particles}, {neighbours})")
    env = {**os.environ, "ONEDNN_VERBOSE": "1", "DNNL_VERBOSE": "1"}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return {"precision": precision, **summarise_verbose(done.stdout.splitlines(), steps)}


def _verbose_steps(precision: str, steps: int, particles: int, neighbours: float) -> None:
    step, _ = _step(precision, particles, neighbours)
    for _ in range(2):
        step()
    print("gns-bench: timed steps start", flush=True)
    for _ in range(steps):
        step()


def summarise_verbose(lines: list[str], steps: int) -> dict[str, Any]:
    """oneDNN verbose lines (`onednn_verbose,[timestamp,]primitive,exec,cpu,<kind>,<implementation>,...,<ms>`)
    after the marker the child prints: milliseconds a step by (kind, implementation), and the total."""
    timed = False
    by_kernel: dict[tuple[str, str], float] = defaultdict(float)
    calls: dict[tuple[str, str], int] = defaultdict(int)
    for line in lines:
        if line.startswith("gns-bench: timed steps start"):
            timed = True
            continue
        fields = line.split(",")
        if not timed or not fields[0].endswith("_verbose") or "exec" not in fields[:6]:  # a timestamp may come first
            continue
        at = fields.index("exec")
        try:
            milliseconds = float(fields[-1])
        except ValueError:
            continue
        key = (fields[at + 2], fields[at + 3])  # after "exec,cpu": the primitive kind, its implementation
        by_kernel[key] += milliseconds / steps
        calls[key] += 1
    total = sum(by_kernel.values())
    rows = sorted(({"kind": kind, "implementation": impl, "calls": calls[kind, impl] // max(steps, 1),
                    "ms_a_step": ms, "share": ms / total if total else float("nan")}
                   for (kind, impl), ms in by_kernel.items()), key=lambda r: -r["ms_a_step"])
    return {"ms_a_step": total, "kernels": rows[:TOP]}


def markdown(results: list[dict[str, Any]], hardware: str) -> str:
    lines = [f"Where a training step's time goes: the paper's model, forward+backward+Adam on {PARTICLES} particles "
             f"at ~{NEIGHBOURS:g} neighbours (a batch of two 1,500-particle frames), eager; {hardware}.", ""]
    for result in results:
        ops, dnn = result["operators"], result["kernels"]
        lines += [f"## {ops['precision']}: {ops['ms_a_step']:.0f} ms a step of operator self time "
                  f"({ops['edges']:,} edges), {dnn['ms_a_step']:.0f} ms of it in oneDNN primitives", "",
                  "| operator | calls a step | ms a step | share |", "|---|---|---|---|"]
        lines += [f"| `{r['operator']}` | {r['calls']} | {r['ms_a_step']:.1f} | {r['share']:.1%} |"
                  for r in ops["operators"]]
        lines += ["", "| oneDNN primitive | implementation (ISA) | calls a step | ms a step | share of oneDNN time |",
                  "|---|---|---|---|---|"]
        lines += [f"| {r['kind']} | `{r['implementation']}` | {r['calls']} | {r['ms_a_step']:.1f} | {r['share']:.1%} |"
                  for r in dnn["kernels"]] or ["| (no oneDNN primitive logged) | | | | |"]
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = bench_parser(__doc__, 3)
    parser.add_argument("--precision", nargs="+", default=["fp32", "bf16"], choices=["fp32", "bf16"])
    args = parser.parse_args(argv)
    hardware = allocated_machine(args.allocator)
    results = [{"operators": operators(p, args.repeats), "kernels": kernels(p, args.repeats, allocator=args.allocator)}
               for p in args.precision]
    text = markdown(results, hardware)
    write_results(args.out, "profile", text, results)


if __name__ == "__main__":
    main()
