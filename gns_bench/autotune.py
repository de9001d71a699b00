"""`train.precision`, `train.compile` and `train.num_threads` = "auto": the fastest settings for this machine,
measured.

What is fastest differs between the machines gns-bench runs on: on an Intel Xeon with AMX, bf16 with
`torch.compile` was fastest; on an AMD EPYC with AVX-512 BF16 and no AMX, bf16 eager beat bf16 compiled
(3.94 against 3.53 training steps a second on GOOP batches of ~2,100 nodes, and compiling cost 52 s). So
nothing is hard-coded: a short probe times a few training steps of each candidate setting on a real batch of
the run, on a copy of the model (the run's own weights and optimiser are untouched), and picks the fastest.
`torch.compile` is chosen only when its saving over the run's steps pays for its compile time.

bf16 is probed only where this machine multiplies in bf16 faster than in fp32 (`matmul_rates`, under a
second): a CPU with no bf16 unit runs bf16 products in a slow fallback. On an AMD EPYC family 25 model 1 (AVX2
only, no AVX-512) the [4096, 128] x [128, 128] product ran 1.5-2.2 GFLOP/s in bf16 against 33-132 in fp32 (one or
two threads, a shared host's spread), and a training step of the paper's model on 2,000 particles took 30.3 s in
bf16 autocast against 4.0 s in fp32 (2 threads): a probe of bf16 there would cost minutes to learn what one
product shows.

The choice is cached per machine (GPU, or CPU model with its family and model number, bf16 features and
thread count; torch's version), model shape and graph size, in `$GNS_BENCH_CACHE` (default
`~/.cache/gns-bench/autotune.json`), so a machine probes once per kind of run. The run records what it used
(the checkpoint keeps it, so a resumed run trains on with the same settings) and the timings behind it.
"""

from __future__ import annotations

import copy
import json
import math
import os
import time
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from gns_bench.config import TrainConfig
from gns_bench.devices import load_average, load_limit, machine_key
from gns_bench.model.simulator import LearnedSimulator, Simulator
from gns_bench.timing import skinny_gemm_gflops, timed_with_warmup

MATMUL_SHAPE = (4096, 128, 128)  # an [E, L] x [L, L] product: the edge MLPs' (Sec. 2, L = 128), the GNS's commonest
WARM_UP_STEPS = 3  # not timed: allocation, autotuning kernels, and compilation for compiled candidates
TIMED_STEPS = 8


@dataclass(frozen=True)
class SpeedSettings:
    precision: str  # "fp32" or "bf16"
    compile: bool
    # how it was chosen: "given" (nothing auto), "probed", or "cached"; and seconds per step measured
    source: str = "given"
    seconds_per_step: dict[str, float] = field(default_factory=dict)  # "<precision>[+compile]" -> seconds
    compile_seconds: float = 0.0
    note: str = ""  # what the choice did not measure, and why (bf16 on a machine with no fast bf16 matmul)
    threads: ThreadChoice | None = None  # `train.num_threads = "auto"`: the count chosen, and how

    def describe(self) -> str:
        settings = f"{self.precision}{' compiled' if self.compile else ''}"
        note = f"; {self.note}" if self.note else ""
        threads = f"; {self.threads.describe()}" if self.threads else ""
        if self.source == "given":
            return settings + (f" ({self.note})" if self.note else "") + threads
        timings = ", ".join(f"{name} {seconds:.3g} s" for name, seconds in sorted(self.seconds_per_step.items()))
        return f"{settings} ({self.source}: {timings + ' a step' if timings else 'nothing to time'}{note}){threads}"

    @classmethod
    def from_dict(cls, saved: dict) -> SpeedSettings:
        """As `dataclasses.asdict` wrote it (a checkpoint's, a cache's)."""
        threads = saved.get("threads")
        return cls(**{**saved, "threads": ThreadChoice(**threads) if threads else None})


# `train.num_threads = "auto"`: torch's intra-op threads are not always faster in numbers, and what they buy is not
# a constant of the CPU model. On an AMD EPYC family 25 model 1 (AVX2 only, 2 cores, a KVM guest) a training step of
# the paper's model on 2,000 particles took 4.03 s with two threads against 2.64 s with one in one session, and
# 1.69 s against 2.39 s in the next (reports/NOTES.md).
THREAD_MARGIN = 0.95  # fewer threads than cores are chosen only when they take at most this share of all cores' time


@dataclass(frozen=True)
class ThreadChoice:
    threads: int
    seconds_per_step: dict[str, float] = field(default_factory=dict)  # thread count (as text) -> seconds a step
    source: str = "probed"  # "probed", "cached", "one core" (nothing to choose), or probed under load (not cached)

    def describe(self) -> str:
        timings = ", ".join(f"{count} {seconds:.3g} s" for count, seconds in
                            sorted(self.seconds_per_step.items(), key=lambda item: int(item[0])))
        return (f"{self.threads} thread{'' if self.threads == 1 else 's'} ({self.source}"
                f"{': ' + timings + ' a step by thread count' if timings else ''})")


def thread_counts(cores: int) -> list[int]:
    """The thread counts a probe times on `cores` usable cores: one, the powers of two between, and all."""
    return sorted({cores, *(2 ** k for k in range(cores.bit_length()) if 2 ** k <= cores)})


def choose_threads(step: Callable[[], None], key: str, cores: int, *, use_cache: bool = True,
                   clock: Callable[[], float] = time.perf_counter) -> ThreadChoice:
    """The torch thread count to train with on `cores` usable cores, set before it returns: each of
    `thread_counts(cores)` times `step()` (one training step on a copy of the model), and a count below all cores
    is chosen when it is faster by `THREAD_MARGIN`. Cached under `key` (the machine, the model, the graph size),
    unless the load average after the probe exceeds the cores: with another job on them, two threads ran a
    100-node training step 6.5x slower than one (AVX2 EPYC), which says nothing of the machine alone."""
    counts = thread_counts(cores)
    cache = _read_cache()
    full_key = f"{key} | threads {'/'.join(map(str, counts))}"
    if len(counts) == 1:
        choice = ThreadChoice(cores, source="one core")
    elif use_cache and full_key in cache:
        choice = ThreadChoice(**{**cache[full_key], "source": "cached"})
    else:
        timings = {}
        for count in counts:
            torch.set_num_threads(count)
            timings[str(count)], _ = _time(step, clock)
        fastest = min(timings, key=timings.get)
        chosen = int(fastest) if timings[fastest] <= THREAD_MARGIN * timings[str(cores)] else cores
        load = load_average()
        if load > load_limit(cores, cores):  # another job shared the cores: more threads lose to it than alone
            choice = ThreadChoice(chosen, timings, f"probed under load {load:.1f}, not cached")
        else:
            choice = ThreadChoice(chosen, timings)
            cache[full_key] = {k: v for k, v in asdict(choice).items() if k != "source"}
            _write_cache(cache)
    torch.set_num_threads(choice.threads)
    return choice


@dataclass(frozen=True)
class MatmulRates:
    """GFLOP/s of the `MATMUL_SHAPE` product on one machine, in fp32 and in bf16."""
    fp32: float
    bf16: float

    @property
    def bf16_pays(self) -> bool:
        """Whether bf16 can speed training up here: its products are faster than fp32's. Where they are not,
        the machine has no bf16 unit and runs them in a fallback (see the module's docstring)."""
        return self.bf16 > self.fp32

    def describe(self) -> str:
        rows, inner, cols = MATMUL_SHAPE
        return (f"its [{rows}, {inner}] x [{inner}, {cols}] matmul ran {self.bf16:.3g} GFLOP/s in bf16 against "
                f"{self.fp32:.3g} in fp32 here")


def matmul_rates(device: torch.device, *, use_cache: bool = True) -> MatmulRates:
    """This machine's rate for the GNS's commonest product in fp32 and in bf16 (`timing.skinny_gemm_gflops`, as
    the bench measures it), cached per machine like the training probe's choice."""
    key = f"{machine_key(device)} | matmul {'x'.join(map(str, MATMUL_SHAPE))}"
    cache = _read_cache()
    if use_cache and key in cache:
        return MatmulRates(**cache[key])
    rows, width, _ = MATMUL_SHAPE
    result = MatmulRates(fp32=skinny_gemm_gflops(rows, width, torch.float32, device),
                         bf16=skinny_gemm_gflops(rows, width, torch.bfloat16, device))
    cache[key] = asdict(result)
    _write_cache(cache)
    return result


def candidates(config: TrainConfig) -> list[tuple[str, bool]]:
    precisions = ["fp32", "bf16"] if config.precision == "auto" else [config.precision]
    compiles = [False, True] if config.compile == "auto" else [bool(config.compile)]
    return [(p, c) for p in precisions for c in compiles]


def label(precision: str, compiled: bool) -> str:
    return precision + ("+compile" if compiled else "")


def cache_path() -> Path:
    root = os.environ.get("GNS_BENCH_CACHE") or Path.home() / ".cache" / "gns-bench"
    return Path(root) / "autotune.json"


def cache_key(config: TrainConfig, simulator: Simulator, nodes: int, device: torch.device) -> str:
    """The machine, the model's shape and the graph size (to a power of two) a choice holds for."""
    parameters = sum(p.numel() for p in simulator.parameters())
    shape = f"{getattr(simulator, 'architecture', 'gns')} {parameters} parameters D{simulator.dim}"
    model = getattr(simulator, "config", None)
    if hasattr(model, "shared_processor"):  # the GNS's processor settings (Sec. 4.2)
        shape += f" M{model.message_passing_steps} shared{int(model.shared_processor)} global{int(model.global_latent)}"
    size = 2 ** round(math.log2(max(nodes, 1)))
    return (f"{machine_key(device)} | {shape} | ~{size} nodes | batch {config.batch_size} | "
            f"{'+'.join(label(p, c) for p, c in candidates(config))}")


def choose(config: TrainConfig, simulator: Simulator, step_fn: Callable[[LearnedSimulator, str], None],
           nodes: int, device: torch.device, steps_left: int, *, use_cache: bool = True) -> SpeedSettings:
    """The settings to train with. Nothing auto: the config's own. Otherwise the cached choice for this
    machine, model and graph size, or a probe: `step_fn(model, precision)` runs one training step of `model`
    (a copy of `simulator`, compiled for compiled candidates) in `precision`."""
    options, note = candidates(config), ""
    if any(precision == "bf16" for precision, _ in options) and not (rates := matmul_rates(device)).bf16_pays:
        if config.precision == "auto":
            options, note = [o for o in options if o[0] != "bf16"], f"bf16 not probed: {rates.describe()}"
        else:
            note = f"bf16 as configured, though {rates.describe()}"
            warnings.warn(f"train.precision = \"bf16\" on a machine with no fast bf16 matmul: {rates.describe()}; "
                          "training will be slower than in fp32", stacklevel=2)
    if len(options) == 1:
        return SpeedSettings(*options[0], source="probed" if config.precision == "auto" else "given", note=note)
    key = cache_key(config, simulator, nodes, device)
    cache = _read_cache()
    if use_cache and key in cache:
        return SpeedSettings.from_dict({**cache[key], "source": "cached"})
    timings, compile_seconds = {}, 0.0
    for precision, compiled in options:
        model = copy.deepcopy(simulator)
        if compiled:
            model.network.compile(dynamic=True)
        timings[label(precision, compiled)], warm_up = _time(lambda model=model, p=precision: step_fn(model, p))
        if compiled:
            compile_seconds = max(compile_seconds, warm_up)
        del model
    best = pick(timings, compile_seconds, steps_left)
    choice = SpeedSettings(best[0], best[1], "probed", timings, compile_seconds, note)
    cache[key] = {k: v for k, v in asdict(choice).items() if k != "source"}
    _write_cache(cache)
    return choice


def _time(step: Callable[[], None], clock: Callable[[], float] = time.perf_counter) -> tuple[float, float]:
    """(seconds a step after warm-up, seconds the warm-up took beyond that many steps: compiling).

    A step's seconds are the median of the timed steps, not their mean: one step that stalled (the process
    paused with SIGSTOP, another job briefly on the cores, a late recompile for a new graph size) must not decide
    the run's settings. In the cpu campaign a probe paused for about three minutes measured compiled bf16 at
    22 s a step against 0.56 s eager (Intel Xeon family 6 model 207), and its run trained eagerly at 1.7 steps a
    second where compiled runs of that model trained at 2.2-2.5."""
    seconds, warm_up = timed_with_warmup(step, TIMED_STEPS, WARM_UP_STEPS, clock=clock)
    return seconds, max(warm_up - WARM_UP_STEPS * seconds, 0.0)


def choose_rollout_compile(simulator: Simulator, rollout_step: Callable[[Simulator], None], precision: str,
                           nodes: int, device: torch.device, steps: int, *, use_cache: bool = True
                           ) -> tuple[SpeedSettings, Simulator | None]:
    """`eval.compile = "auto"`: whether rollouts run faster through a compiled, frozen copy of the network
    (`compiled_for_inference`) over their `steps` steps here, its compiling counted. `rollout_step(model)`
    runs one rollout step of `model`. Cached like training's choice. Returns the choice and, when a probe
    compiled it, that copy (not compiled twice). (The rollout's precision is never "auto": it changes the
    errors a report shows, so a tier fixes it.)"""
    from gns_bench.model.precision import compiled_for_inference

    parameters = sum(p.numel() for p in simulator.parameters())
    key = (f"{machine_key(device)} | rollout {getattr(simulator, 'architecture', 'gns')} {parameters} parameters "
           f"D{simulator.dim} | ~{2 ** round(math.log2(max(nodes, 1)))} nodes | {precision}")
    cache = _read_cache()
    if use_cache and key in cache:
        return SpeedSettings.from_dict({**cache[key], "source": "cached"}), None
    eager, _ = _time(lambda: rollout_step(simulator))
    compiled_model = compiled_for_inference(simulator)
    compiled, compile_seconds = _time(lambda: rollout_step(compiled_model))
    timings = {label(precision, False): eager, label(precision, True): compiled}
    chosen = pick(timings, compile_seconds, steps)
    choice = SpeedSettings(chosen[0], chosen[1], "probed", timings, compile_seconds)
    cache[key] = {k: v for k, v in asdict(choice).items() if k != "source"}
    _write_cache(cache)
    return choice, compiled_model


def pick(timings: dict[str, float], compile_seconds: float, steps_left: int) -> tuple[str, bool]:
    """The setting with the least time for the run's remaining steps, compiling counted once."""
    def total(name: str) -> float:
        return timings[name] * steps_left + (compile_seconds if name.endswith("+compile") else 0.0)

    name = min(timings, key=total)
    return name.removesuffix("+compile"), name.endswith("+compile")


def _read_cache() -> dict[str, dict]:
    try:
        return json.loads(cache_path().read_text())
    except (OSError, ValueError):
        return {}


def _write_cache(cache: dict[str, dict]) -> None:
    path = cache_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp")
    tmp.write_text(json.dumps(cache, indent=1, sort_keys=True) + "\n")
    os.replace(tmp, path)


# `eval.neighbour_skin = "auto"`: Verlet lists (model/neighbours.py) give a fresh search's edges in its order, so
# the only question is time, and it depends on the scene: how fast particles move against R (how often the
# lists go stale), how dense the graph is, the backend and the machine (on the 2-core CPUs the search is 1.6-2.9%
# of a WATERDROP rollout step, on an H200 up to 59% of a 3D one). So a probe times each candidate on true frames.
NEIGHBOUR_SKINS = (0.1, 0.25, 0.5)  # candidate skins, in connectivity radii
SKIN_PROBE_FRAMES = 12  # consecutive true frames a probe segment walks through (one finder each)
SKIN_PROBE_SEGMENTS = 3  # segments spread over the trajectory: its motion changes (blocks at rest, then falling)
SKIN_MARGIN = 0.9  # a skin is chosen only when it takes at most this share of the plain search's time


@dataclass(frozen=True)
class SkinChoice:
    skin: float  # 0: a fresh search every step
    seconds_per_step: dict[float, float]  # candidate skin (0 included) -> seconds of neighbour finding a step
    radius: float

    def describe(self) -> str:
        timings = ", ".join(f"{'none' if skin == 0 else f'{skin / self.radius:g} R'} {seconds * 1e3:.3g} ms"
                            for skin, seconds in sorted(self.seconds_per_step.items()))
        chosen = "none" if self.skin == 0 else f"{self.skin:.4g} ({self.skin / self.radius:g} R)"
        return f"skin {chosen} (probed on true frames: {timings} a step)"


def choose_neighbour_skin(make_finder: Callable[[float], Callable[[torch.Tensor], torch.Tensor]],
                          positions: torch.Tensor, radius: float, *, skins: tuple[float, ...] = NEIGHBOUR_SKINS,
                          frames: int = SKIN_PROBE_FRAMES, segments: int = SKIN_PROBE_SEGMENTS,
                          margin: float = SKIN_MARGIN, clock: Callable[[], float] = time.perf_counter) -> SkinChoice:
    """The skin to roll out with: each candidate (`skins` x radius, and none) walks `segments` runs of `frames`
    consecutive true frames (`positions` [T, N, D]) through a fresh finder (`make_finder(skin)`: positions [N, D]
    -> edges, as the rollout would search with that skin), twice; its time is the faster pass. A skin is chosen
    when it beats none by `margin`, so noise does not pick one."""
    count = positions.shape[0]
    length = min(frames, count)
    starts = sorted({round(i * (count - length) / max(segments, 1)) for i in range(segments)})
    timings = {}
    for skin in (0.0, *(s * radius for s in skins)):
        passes = []
        for _ in range(2):
            started = clock()
            for start in starts:
                finder = make_finder(skin)
                for frame in range(start, start + length):
                    finder(positions[frame])
            passes.append(clock() - started)
        timings[skin] = min(passes) / (len(starts) * length)
    best = min(timings, key=timings.get)
    chosen = best if best > 0 and timings[best] <= margin * timings[0.0] else 0.0
    return SkinChoice(chosen, timings, radius)
