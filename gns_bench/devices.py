"""Where torch runs: the device a run asks for, resolved once."""

from __future__ import annotations

import os
from pathlib import Path

import torch


def resolve_device(name: str) -> torch.device:
    """`"auto"` picks CUDA when present, else the CPU; any other name is torch's."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def _first_processor(cpuinfo: str | Path = "/proc/cpuinfo") -> dict[str, str]:
    """The fields of the first processor listed in /proc/cpuinfo ("model name", "flags", ...); {} where the file
    is missing."""
    fields: dict[str, str] = {}
    try:
        for line in open(cpuinfo, encoding="utf-8"):
            if not line.strip():
                if fields:
                    break
                continue
            key, _, value = line.partition(":")
            fields.setdefault(key.strip(), value.strip())
    except OSError:
        return {}
    return fields


def cpu_model(cpuinfo: str | Path = "/proc/cpuinfo") -> str:
    """The CPU's model name (/proc/cpuinfo), else what the platform says."""
    import platform

    return _first_processor(cpuinfo).get("model name") or platform.processor() or platform.machine()


def cpu_identity(cpuinfo: str | Path = "/proc/cpuinfo") -> str:
    """Which generation the CPU is, where its model name does not say ("AMD EPYC" names both Zen 4 and Zen 5
    parts): its family, model and stepping and its clock, from /proc/cpuinfo; "" where that file is missing.
    It tells generations apart, not a busier host: one run's step rate moved by a third between two sessions
    on the same machine (reports/NOTES.md)."""
    fields = _first_processor(cpuinfo)
    generation = _generation(fields)
    parts = [generation] if generation else []
    if "stepping" in fields:
        parts.append(f"stepping {fields['stepping']}")
    if "cpu MHz" in fields:
        parts.append(f"{float(fields['cpu MHz']):.0f} MHz")
    return ", ".join(parts)


def cpu_generation(cpuinfo: str | Path = "/proc/cpuinfo") -> str:
    """The CPU's family and model ("family 25, model 17"): what tells two generations sold under one model name
    apart, without the stepping and clock that `cpu_identity` adds; "" where /proc/cpuinfo is missing."""
    return _generation(_first_processor(cpuinfo))


def _generation(fields: dict[str, str]) -> str:
    return ", ".join(f"{name} {fields[key]}" for name, key in (("family", "cpu family"), ("model", "model"))
                     if key in fields)


def cpu_features(cpuinfo: str | Path = "/proc/cpuinfo") -> list[str]:
    """The CPU features that decide which training settings are fastest: the bf16 matrix units (AMX on Intel,
    AVX-512 BF16 on AMD and Intel) and AVX-512 itself. A model name such as "AMD EPYC" does not tell them."""
    flags = set(_first_processor(cpuinfo).get("flags", "").split())
    return [flag for flag in ("amx_bf16", "amx_tile", "avx512_bf16", "avx512f") if flag in flags]


def machine_slug(device: torch.device, cpuinfo: str | Path = "/proc/cpuinfo") -> str:
    """A folder name for what a benchmark ran on: the GPU's name, or the CPU model with its generation and its
    bf16 matrix units ("amd-epyc-family-26-model-2-avx512bf16"), which decide what is fastest on it. The
    generation keeps two machines sold under one model name apart: "AMD EPYC" with AVX-512 BF16 names a family-25
    part whose bf16 GEMM ran 417 GFLOP/s on 2 threads and a family-26 one that ran 964 (reports/bench)."""
    import re

    if device.type == "cuda":
        name = f"cuda {torch.cuda.get_device_name(device)}"
    else:
        features = cpu_features(cpuinfo)
        unit = "amx" if "amx_tile" in features else "avx512bf16" if "avx512_bf16" in features else ""
        name = f"{cpu_model(cpuinfo)} {cpu_generation(cpuinfo)} {unit}"
    name = re.sub(r"\((r|tm)\)", "", name.lower())
    return re.sub(r"[^a-z0-9]+", "-", name).strip("-")


def machine_key(device: torch.device) -> str:
    """What a speed measurement holds for: the GPU, or the CPU model, its generation, its relevant features and
    the thread count; with torch's version. The generation matters: two "AMD EPYC" machines with the same
    features differ in speed (CONTINUOUS trained at 1.56 steps/s on CPU family 25, where its probe on family 26
    had measured 3.13; reports/NOTES.md)."""
    if device.type == "cuda":
        name = torch.cuda.get_device_name(device)
    else:
        generation = cpu_generation()
        name = (f"{cpu_model()}{f' ({generation})' if generation else ''} [{' '.join(cpu_features())}] "
                f"x{torch.get_num_threads()}")
    return f"{name}; torch {torch.__version__}"


def usable_core_ids() -> list[int]:
    """The cores this process may run on (its CPU affinity: a container's or a job scheduler's share)."""
    try:
        return sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return list(range(os.cpu_count() or 1))


def usable_cores() -> int:
    return len(usable_core_ids())


def set_threads(requested: int | None) -> int:
    """torch's intra-op threads: the request (or every usable core), never more than the usable cores (two
    2-thread jobs on 2 cores made a training step about 10x slower). Returns the count set."""
    threads = min(requested or usable_cores(), usable_cores())
    torch.set_num_threads(threads)
    return threads


def load_average() -> float:
    """The 1-minute load average (runnable and running threads, a stopped process not counted); NaN where
    the system does not say."""
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return float("nan")


def load_limit(own_threads: int, cores: int | None = None) -> float:
    """The 1-minute load average above which another job shares the cores (`cores`, or the usable ones) with a
    process running `own_threads` threads: its own threads count in the load, so more than the cores (or its
    threads) is someone else's (two 2-thread jobs on 2 cores made a training step about 10x slower)."""
    return max(cores or usable_cores(), own_threads) + 0.5


# glibc's mallopt parameters (malloc.h): M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_MAX.
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_MAX, _M_ARENA_MAX = -1, -2, -4, -8
KEEP_MAPPED = {"trim_threshold": 64 << 30, "top_pad": 256 << 20, "mmap_max": 0, "arena_max": 1}


def keep_memory_mapped() -> str:
    """Make glibc's malloc keep freed memory mapped: no mmap for large blocks (each would go back to the kernel
    when freed and fault in again, page by page, when the next step asks for it), no trimming of the heap's
    top, 256 MiB of padding when it grows, and one arena for every thread (a worker thread's own arena hands
    its freed pages back whatever the trim threshold: with 2 threads the first three settings alone left the
    faults as they were). GLIBC_TUNABLES=glibc.malloc.mmap_max=0:glibc.malloc.trim_threshold=68719476736:
    glibc.malloc.top_pad=268435456 does the first three before the process starts; this sets all four from
    inside it (they hold for allocations from now on). A training step of the paper's model frees and
    reallocates hundreds of MB of activations: the first three made fp32 training 1.9x faster on an Intel Xeon
    (system time 49 s -> 6 s in one side-by-side iteration). Returns what it set, or "" where the C library is
    not glibc."""
    import ctypes
    import ctypes.util

    if os.name != "posix":
        return ""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl, macOS: no mallopt with these parameters
        return ""
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    trim = min(KEEP_MAPPED["trim_threshold"], 2**31 - 1)  # mallopt takes an int: 2 GiB is as good as never
    done = [mallopt(_M_MMAP_MAX, KEEP_MAPPED["mmap_max"]), mallopt(_M_TRIM_THRESHOLD, trim),
            mallopt(_M_TOP_PAD, KEEP_MAPPED["top_pad"]), mallopt(_M_ARENA_MAX, KEEP_MAPPED["arena_max"])]
    if not all(done):
        return ""
    return (f"glibc malloc kept mapped (mmap_max 0, trim_threshold {trim}, top_pad {KEEP_MAPPED['top_pad']}, "
            "arena_max 1)")


def apply_allocator(setting: str) -> str:
    """`train.allocator`: keep freed memory mapped ("keep"; "auto" unless GLIBC_TUNABLES says otherwise) or leave
    the allocator as it is ("system"). Returns what the process runs with, for the run's record."""
    tunables = os.environ.get("GLIBC_TUNABLES", "")
    if setting == "system" or (setting == "auto" and tunables):
        return "system" + (f" (GLIBC_TUNABLES={tunables})" if tunables else "")
    return keep_memory_mapped() or "system (no glibc mallopt here)"
