"""`gns-bench bench`: one process, one run, every ratio measured against this machine's own limits.

Writes `bench.json`, `README.md` (tables) and PNG plots into the output folder and logs them to MLflow
(experiment `bench`). Scaling points run in fresh subprocesses so each one's peak memory is its own.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch

from gns_bench import autotune, tracking
from gns_bench.bench.baseline import concatenated_baseline
from gns_bench.bench.measure import (
    build_model,
    forward_flops,
    gemm_peak_gflops,
    rollout_breakdown,
    skinny_gemm_gflops,
    synthetic_scene,
    synthetic_train_step,
    train_step_seconds,
)
from gns_bench.config import ModelConfig, TrainConfig
from gns_bench.datasets import default_connectivity_radius
from gns_bench.devices import cpu_generation, machine_key, resolve_device, usable_cores

# Paper domains for the inference-time table (App. C.6): id, dim, max particles (Table 1), radius.
INFERENCE_DOMAINS = [("waterdrop", 2, 1000), ("water", 2, 1900), ("sand", 2, 2000), ("goop", 2, 1900),
                     ("waterramps", 2, 2300), ("continuous", 2, 4300), ("boxbath", 3, 1000),
                     ("water-3d-s", 3, 5800), ("water-3d", 3, 13000), ("goop-3d", 3, 14000), ("sand-3d", 3, 20000)]


# The dtype a precision's matmuls run in (bf16 autocast multiplies in bfloat16), for the GEMM rates measured
# beside each timing.
GEMM_DTYPE = {"fp32": torch.float32, "bf16": torch.bfloat16}

OURS = "gns-bench (split first edge layer)"
BASELINE = "PyG MessagePassing, concatenated inputs"


@dataclass
class BenchSettings:
    device: str = "auto"
    train_particles: int = 2000  # WaterDrop-like 2D graph: ~2k nodes, ~30k edges
    scaling_2d: tuple[int, ...] = (1000, 4000, 16000, 85000)
    scaling_3d: tuple[int, ...] = (1000, 10000, 100000)
    inference_domains: list[tuple[str, int, int]] = field(default_factory=lambda: list(INFERENCE_DOMAINS))
    repeats: int = 5
    gemm_sizes: tuple[int, ...] = (1024, 2048, 4096)
    compile: bool = True  # also time the training step under torch.compile (~1 min of compilation each)
    # ... and the rollout step of these domains as `eval.compile` runs it (~15 s of compiling each)
    compiled_rollout_domains: tuple[str, ...] = ("waterdrop",)
    # the precisions every variant is timed in; empty: fp32, and bf16 where this machine multiplies faster in it
    # (`bench_precisions`)
    precisions: tuple[str, ...] = ()
    # the one-step forward's particle counts and windows batched into a graph; empty: bench/one_step.py's own
    one_step_particles: tuple[int, ...] = ()
    one_step_windows: tuple[int, ...] = ()

    @classmethod
    def quick(cls) -> BenchSettings:
        """Seconds, not minutes: for tests and a first look."""
        return cls(train_particles=400, scaling_2d=(500, 1000), scaling_3d=(500,),
                   inference_domains=[("waterdrop", 2, 1000), ("boxbath", 3, 1000)], repeats=2, compile=False,
                   one_step_particles=(400,), one_step_windows=(1, 2, 4))

    @classmethod
    def tiny(cls) -> BenchSettings:
        """The smallest run that exercises every measurement (tests)."""
        return cls(train_particles=100, scaling_2d=(200,), scaling_3d=(), inference_domains=[("waterdrop", 2, 200)],
                   repeats=1, gemm_sizes=(256,), compile=False, one_step_particles=(100,), one_step_windows=(1, 2))


def bench_precisions(settings: BenchSettings, device: torch.device) -> tuple[tuple[str, ...], str]:
    """The precisions to time every variant in, and what was left out and why: the settings' own, or
    `machine_precisions`."""
    if settings.precisions:
        return tuple(settings.precisions), ""
    return machine_precisions(device)


def machine_precisions(device: torch.device) -> tuple[tuple[str, ...], str]:
    """fp32, and bf16 where its products run faster than fp32's (`autotune.matmul_rates`), with what was left out
    and why: a CPU with no bf16 unit runs them in a fallback, where a benchmark's bf16 rows would take hours to say
    what one product shows (on an AVX2-only AMD EPYC, family 25 model 1, a 4096-square bf16 product ran over a
    minute)."""
    rates = autotune.matmul_rates(device)
    if rates.bf16_pays:
        return ("fp32", "bf16"), ""
    return ("fp32",), f"bf16 left out: {rates.describe()} (no bf16 unit)"


def measure_training(settings: BenchSettings, device: torch.device, precisions: tuple[str, ...] = ("fp32", "bf16")
                     ) -> list[dict[str, Any]]:
    scene = synthetic_scene(settings.train_particles, 2)
    rows = []
    peaks = {p: gemm_peak_gflops(GEMM_DTYPE[p], device, settings.gemm_sizes, settings.repeats) for p in precisions}
    model = build_model(ModelConfig(), scene, device)
    edges = int(model.build_graph(scene.window[:, -1].to(device)).shape[1])
    skinny = {p: skinny_gemm_gflops(edges, 128, GEMM_DTYPE[p], device) for p in precisions}
    flops = 3 * forward_flops(model, scene.window.shape[0], edges)  # forward + backward ~ 3 x forward
    variants = [(OURS, False, lambda: build_model(ModelConfig(), scene, device)),
                (BASELINE, False, lambda: concatenated_baseline(build_model(ModelConfig(), scene, device)))]
    if settings.compile:
        variants.insert(1, (OURS, True, lambda: build_model(ModelConfig(), scene, device)))
    for name, compiled, make in variants:
        for precision in precisions:
            seconds, loss = train_step_seconds(make(), scene, device, precision, settings.repeats, compiled)
            rate = flops / seconds / 1e9
            rows.append({"model": name, "compiled": compiled, "precision": precision,
                         "nodes": scene.window.shape[0], "edges": edges,
                         "step_s": seconds, "steps_per_s": 1 / seconds, "gflops": rate,
                         "gemm_peak_gflops": peaks[precision], "fraction_of_peak": rate / peaks[precision],
                         "skinny_gemm_gflops": skinny[precision], "fraction_of_skinny": rate / skinny[precision],
                         "loss_after_steps": loss})
    return rows


def measure_steadiness(train: list[dict[str, Any]], settings: BenchSettings, device: torch.device
                       ) -> dict[str, dict[str, float]]:
    """The square-GEMM rate measured again at the end of the run, beside the one the training rows were judged
    against at its start. A shared host's speed differs between sessions (an Intel Xeon of one CPU model measured
    2,368 bf16 GFLOP/s in one session and 679 in another) and can drift within one; ratios of numbers taken
    minutes apart are only as good as it holds."""
    start = {row["precision"]: row["gemm_peak_gflops"] for row in train}
    return {precision: {"start": rate,
                        "end": gemm_peak_gflops(GEMM_DTYPE[precision], device, settings.gemm_sizes, settings.repeats)}
            for precision, rate in start.items()}


def measure_autotune(settings: BenchSettings, device: torch.device, steps: int = 20_000) -> dict[str, Any]:
    """What `train.precision = "auto"` and `train.compile = "auto"` pick for the bench's training scene (its own
    short probe, no cache), to set against the variants the bench times at length."""
    scene = synthetic_scene(settings.train_particles, 2)
    model = build_model(ModelConfig(), scene, device)
    window, types = scene.window.to(device), scene.particle_type.to(device)
    edges = model.build_graph(window[:, -1])
    optimisers: dict[int, torch.optim.Optimizer] = {}

    def step(candidate, precision: str) -> None:
        optimiser = optimisers.setdefault(id(candidate), torch.optim.Adam(candidate.parameters(), lr=0.0))
        synthetic_train_step(candidate, optimiser, window, types, edges, precision)

    config = TrainConfig(precision="auto", compile="auto" if settings.compile else False)
    choice = autotune.choose(config, model, step, window.shape[0], device, steps, use_cache=False)
    picked = {"precision": choice.precision, "compiled": choice.compile, "probe_step_s": choice.seconds_per_step,
              "compile_s": choice.compile_seconds, "steps_assumed": steps, "note": choice.note}
    if device.type == "cpu":  # and what `train.num_threads = "auto"` picks, in fp32; the bench runs on every core
        threads, probe_model = torch.get_num_threads(), build_model(ModelConfig(), scene, device)
        try:
            key = f"{machine_key(device)} | bench's training scene, {window.shape[0]} nodes, fp32"
            counts = autotune.choose_threads(lambda: step(probe_model, "fp32"), key, usable_cores(), use_cache=False)
        finally:
            torch.set_num_threads(threads)
        picked["threads"] = {"chosen": counts.threads, "step_s": counts.seconds_per_step}
    return picked


def measure_inference(settings: BenchSettings, device: torch.device, precisions: tuple[str, ...] = ("fp32", "bf16")
                      ) -> list[dict[str, Any]]:
    """A rollout step of each domain's size, eager in fp32 and bf16, then compiled (`eval.compile`) for
    `settings.compiled_rollout_domains` when `settings.compile` (compiled last: see `rollout_breakdown`).
    Each row carries the time the network's matmuls alone need at the [E, 128] x [128, 128] GEMM rate
    measured here (`matmul_floor_s`): how close a step is to what this machine's matmuls allow."""
    rows, skinny = [], {}
    variants = [(False, domain) for domain in settings.inference_domains]
    if settings.compile:
        variants += [(True, domain) for domain in settings.inference_domains
                     if domain[0] in settings.compiled_rollout_domains]
    for compiled, (domain, dim, particles) in variants:
        scene = synthetic_scene(particles, dim, default_connectivity_radius(domain))  # as its datasets carry it
        model = build_model(ModelConfig(), scene, device)
        for precision in precisions:
            b = rollout_breakdown(model, scene, device, precision, settings.repeats, compiled)
            dtype = GEMM_DTYPE[precision]
            if (b.num_edges, precision) not in skinny:
                skinny[b.num_edges, precision] = skinny_gemm_gflops(b.num_edges, 128, dtype, device)
            flops = forward_flops(model, particles, b.num_edges)
            rows.append({"domain": domain, "dim": dim, "precision": precision, "compiled": compiled,
                         "particles": particles, "edges": b.num_edges, "step_s": b.total_s,
                         "neighbour_search_s": b.neighbour_search_s, "features_s": b.features_s, "gnn_s": b.gnn_s,
                         "integration_s": b.integration_s, "verlet_search_s": b.verlet_search_s,
                         "search_share": b.neighbour_search_s / b.total_s,
                         "search_and_graph_share": (b.neighbour_search_s + b.features_s) / b.total_s,
                         "forward_gflop": flops / 1e9,
                         "matmul_floor_s": flops / (skinny[b.num_edges, precision] * 1e9)})
    return rows


SCALING_DOMAINS = {2: "waterdrop", 3: "water-3d"}  # whose radius the scaling scenes take


def peak_rss_mb() -> float:
    """This process's peak resident memory (VmHWM). Unlike getrusage's ru_maxrss, which a child started by
    fork and exec inherits from its parent, it belongs to this process alone."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmHWM in /proc/self/status (Linux only)")


def scaling_point(particles: int, dim: int, device: str) -> dict[str, Any]:
    """One rollout step at this size (run in a fresh process by `measure_scaling`)."""
    torch_device = resolve_device(device)
    baseline_mb = peak_rss_mb()
    # The scene's density is fixed by its neighbour count; the radius is a real domain's of that dimension.
    scene = synthetic_scene(particles, dim, default_connectivity_radius(SCALING_DOMAINS[dim]))
    model = build_model(ModelConfig(), scene, torch_device)
    b = rollout_breakdown(model, scene, torch_device, "fp32", repeats=1)
    if torch_device.type == "cuda":
        peak_mb = torch.cuda.max_memory_allocated() / 2**20
    else:
        peak_mb = peak_rss_mb()
    return {"dim": dim, "particles": particles, "edges": b.num_edges, "step_s": b.total_s,
            "search_share": b.neighbour_search_s / b.total_s, "peak_memory_mb": peak_mb,
            "process_baseline_mb": baseline_mb if torch_device.type == "cpu" else 0.0, "device": str(torch_device)}


def measure_scaling(settings: BenchSettings, timeout_s: int = 1800) -> list[dict[str, Any]]:
    rows = []
    for dim, sizes in ((2, settings.scaling_2d), (3, settings.scaling_3d)):
        for particles in sizes:
            code = ("import json; from gns_bench.bench.run import scaling_point; "
                    f"print(json.dumps(scaling_point({particles}, {dim}, {settings.device!r})))")
            done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout_s,
                                  env={**os.environ, "PYTHONWARNINGS": "ignore"})
            if done.returncode != 0:
                rows.append({"dim": dim, "particles": particles, "error": done.stderr.strip().splitlines()[-1:]})
            else:
                rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
    return rows


def bench_dir(root: Path, device: str = "auto") -> Path:
    """`root/<machine>`: each kind of machine keeps its own benchmark (devices.machine_slug)."""
    from gns_bench.devices import machine_slug

    return root / machine_slug(resolve_device(device))


def run_bench(out_dir: str | Path, settings: BenchSettings | None = None,
              log_to_mlflow: bool = True) -> dict[str, Any]:
    from gns_bench.bench import one_step, skips
    from gns_bench.bench.report import write_bench_report

    settings = settings or BenchSettings()
    device = resolve_device(settings.device)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    results: dict[str, Any] = {
        "environment": {"hardware": tracking.hardware_description(str(device)), "device": str(device),
                        "cpu": cpu_generation() if device.type == "cpu" else "",
                        "torch": torch.__version__, "threads": torch.get_num_threads()},
        "settings": asdict(settings),
    }
    precisions, left_out = bench_precisions(settings, device)
    results["precisions"], results["left_out"] = list(precisions), left_out
    print(f"bench on {results['environment']['hardware']} ({', '.join(precisions)}"
          f"{'; ' + left_out if left_out else ''}): training step...", flush=True)
    results["train"] = measure_training(settings, device, precisions)
    print("what train.precision/compile = auto picks...", flush=True)
    results["autotune"] = measure_autotune(settings, device)
    print("rollout steps of the paper's domains...", flush=True)
    results["inference"] = measure_inference(settings, device, precisions)
    print("the kinematic particles' skip...", flush=True)
    results["skips"] = skips.measure(settings.train_particles, repeats=settings.repeats, precisions=precisions)
    print("the static encodings' reuse...", flush=True)
    results["static_encodings"] = skips.measure_encodings(settings.train_particles, repeats=settings.repeats,
                                                          precisions=precisions)
    print("windows a one-step forward...", flush=True)
    results["one_step"] = one_step.measure(settings.one_step_particles or one_step.PARTICLES,
                                           settings.one_step_windows or one_step.WINDOWS, repeats=settings.repeats)
    print("scaling in particle count...", flush=True)
    results["scaling"] = measure_scaling(settings)
    results["steadiness"] = measure_steadiness(results["train"], settings, device)
    (out_dir / "bench.json").write_text(json.dumps(results, indent=2) + "\n")
    paths = write_bench_report(results, out_dir)
    if log_to_mlflow:
        _log(results, [out_dir / "bench.json", *paths])
    return results


def _log(results: dict[str, Any], paths: list[Path]) -> None:
    device = results["environment"]["device"]
    with tracking.start_run("bench", f"bench-{device}", tags=tracking.environment_tags(device)) as run:
        metrics = {}
        for row in results["train"]:
            key = ("split_compiled" if row.get("compiled") else "split") if row["model"] == OURS else "concat"
            metrics[f"train/{key}_{row['precision']}_steps_per_s"] = row["steps_per_s"]
            metrics[f"train/{key}_{row['precision']}_fraction_of_peak"] = row["fraction_of_peak"]
        for row in results["inference"]:
            variant = "_compiled" if row.get("compiled") else ""
            metrics[f"rollout/{row['domain']}_{row['precision']}{variant}_step_s"] = row["step_s"]
        run.log_metrics(metrics)
        for path in paths:
            run.log_artifact(path, "bench")
