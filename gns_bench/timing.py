"""Timing on the device at hand: a median over repeats, and the rate of the GNS's commonest product.

Shared by the bench (`gns_bench/bench/measure.py`) and the speed choices made at run time
(`gns_bench/autotune.py`).
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import torch


def timed(fn: Callable[[], object], repeats: int = 5, warmup: int = 2, sync: Callable[[], None] | None = None
          ) -> float:
    """Median wall time of `fn` in seconds."""
    return timed_with_warmup(fn, repeats, warmup, sync)[0]


def timed_with_warmup(fn: Callable[[], object], repeats: int, warmup: int, sync: Callable[[], None] | None = None,
                      clock: Callable[[], float] = time.perf_counter) -> tuple[float, float]:
    """(median wall time of `repeats` calls of `fn` after `warmup` untimed ones, seconds the warm-up took): the
    median, so that one call that stalled (a paused process, another job on the cores) does not decide."""
    started = clock()
    for _ in range(warmup):
        fn()
    warm_up = clock() - started
    times = []
    for _ in range(repeats):
        if sync:
            sync()
        start = clock()
        fn()
        if sync:
            sync()
        times.append(clock() - start)
    return float(statistics.median(times)), warm_up


def skinny_gemm_gflops(rows: int, width: int, dtype: torch.dtype, device: torch.device, repeats: int = 5) -> float:
    """The rate of the GEMM shape that dominates the GNS: [E, L] @ [L, L]."""
    a = torch.randn(rows, width, device=device).to(dtype)
    b = torch.randn(width, width, device=device).to(dtype)
    seconds = timed(lambda: a @ b, repeats, sync=device_sync(device))
    return 2 * rows * width * width / seconds / 1e9


def device_sync(device: torch.device) -> Callable[[], None] | None:
    return torch.cuda.synchronize if device.type == "cuda" else None
