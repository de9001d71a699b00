"""How fast a run would train here: steps a second of its own config on its own data, measured.

A tier defines runs by steps, not seconds, so that results do not depend on the machine's speed;
the steps are chosen from a measured step rate. `measure_step_rate` runs the one training loop (`train`) for a
few steps on the run's dataset, in a scratch directory, with the precision and compile setting the run itself
would use (`auto` resolves as it will in the run, from the same probe and cache), and times the steps after a
warm-up. `gns-bench sweep FILE --tier T --time` and `gns-bench campaign FILE --tier T --time` print it for
every planned run with the training time its steps would take.

Window sizes vary (trajectories of a few hundred to several thousand particles), so the rate is a mean over
the measured steps' batches, which are the run's own first batches (every batch comes from (seed, step)).
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from gns_bench.config import Config
from gns_bench.train.loop import train

RECOMPILE_FACTOR = 3.0  # a measured step slower than this many medians counts as the median (`steady_rate`)


@dataclass(frozen=True)
class StepRate:
    steps_per_second: float
    settings: str  # the precision and compile setting the steps ran with, as the run would ("bf16 compiled")
    measured_steps: int

    def seconds_for(self, steps: int) -> float:
        return steps / self.steps_per_second


def steady_rate(durations: list[float]) -> float:
    """Steps a second over measured step durations, a step slower than `RECOMPILE_FACTOR` x the median counted as
    the median: torch.compile specialising the graph to a new batch shape, which a whole run pays once and a
    few-step probe would spread over every step (SANDRAMPS, AMD EPYC: 0.76-1.68 steps/s over 20 compiled steps,
    4.54 over 60, 3.7 eager)."""
    median = sorted(durations)[len(durations) // 2]
    return len(durations) / sum(d if d <= RECOMPILE_FACTOR * median else median for d in durations)


def measure_step_rate(config: Config, dataset_dir: str | Path, *, steps: int = 20, warm_up: int = 5) -> StepRate:
    """Training steps a second of `config` on `dataset_dir`'s train split: the mean over `steps` steps of the
    run's own loop after `warm_up` untimed ones (allocation, compiling), by `steady_rate`. The loop runs as the
    start of the whole run (`train(stop_after=...)`), so `auto` settings are chosen for the run's length, as the
    run will choose them. Nothing is logged or kept."""
    if steps < 1 or warm_up < 1:
        raise ValueError(f"measure_step_rate: steps ({steps}) and warm_up ({warm_up}) must be >= 1")
    total = warm_up + steps
    if config.train.steps < total:
        raise ValueError(f"measure_step_rate: the run has {config.train.steps} steps, fewer than the {total} "
                         "to measure")
    probe = dataclasses.replace(config, train=dataclasses.replace(
        config.train, log_every=1, checkpoint_every=config.train.steps, eval_every=0, max_wall_seconds=None))
    stamps: dict[int, float] = {}

    def on_log(step: int, _metrics: dict[str, float]) -> None:
        stamps[step] = time.perf_counter()

    with tempfile.TemporaryDirectory(prefix="gns-bench-rate-") as scratch:
        result = train(probe, dataset_dir, scratch, on_log=on_log, progress=False, stop_after=total)
    rate = steady_rate([stamps[step] - stamps[step - 1] for step in range(warm_up + 1, total + 1)])
    speed = result.speed
    settings = f"{speed.precision}{' compiled' if speed.compile else ''}" if speed else config.train.precision
    return StepRate(rate, settings, steps)
