"""The one place that initialises Taichi.

CPU by default; CUDA when the machine has it, unless `GNS_BENCH_TAICHI_ARCH=cpu` says otherwise.
`GNS_BENCH_TAICHI_DEBUG=1` turns on Taichi's debug mode: every field and ndarray access is bounds-checked
(several times slower; the tests run the solvers this way once, tests/physics/test_bounds.py).
Determinism does not depend on the thread count: the MPM particle-to-grid scatter accumulates in
fixed-point integers (see mpm.py), whose atomic adds commute, so float summation order cannot leak
into the data. Floating-point settings are pinned (no fast-math) so that one machine always gives
the same bits.
"""

from __future__ import annotations

import os

import taichi as ti

_ARCH_ENV = "GNS_BENCH_TAICHI_ARCH"
_THREADS_ENV = "GNS_BENCH_TAICHI_THREADS"
_DEBUG_ENV = "GNS_BENCH_TAICHI_DEBUG"
_state: dict[str, str] = {}


def _cuda_available() -> bool:
    # The driver's control device exists only where an NVIDIA driver is loaded; importing torch to ask
    # would cost seconds per process. Taichi itself falls back to CPU if CUDA then fails to start.
    return os.path.exists("/dev/nvidiactl")


def ensure_taichi() -> str:
    """Initialise Taichi once per process and return the arch name ("x64", "arm64" or "cuda")."""
    if _state:
        return _state["arch"]
    wanted = os.environ.get(_ARCH_ENV, "auto").lower()
    if wanted not in ("auto", "cpu", "cuda"):
        raise ValueError(f"{_ARCH_ENV}={wanted!r}: expected auto, cpu or cuda")
    use_cuda = wanted == "cuda" or (wanted == "auto" and _cuda_available())
    debug = os.environ.get(_DEBUG_ENV, "0")
    if debug not in ("0", "1"):
        raise ValueError(f"{_DEBUG_ENV}={debug!r}: expected 0 or 1")
    kwargs = dict(default_fp=ti.f32, default_ip=ti.i32, fast_math=False, random_seed=0,
                  offline_cache=True, log_level=ti.WARN, debug=debug == "1")
    if use_cuda:
        ti.init(arch=ti.cuda, **kwargs)
    else:
        threads = int(os.environ.get(_THREADS_ENV, "0")) or (os.cpu_count() or 1)
        ti.init(arch=ti.cpu, cpu_max_num_threads=threads, **kwargs)
    _state["arch"] = str(ti.lang.impl.current_cfg().arch.name)
    return _state["arch"]
