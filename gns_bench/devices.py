"""Where torch runs: the device a run asks for, resolved once."""

from __future__ import annotations

import torch


def resolve_device(name: str) -> torch.device:
    """`"auto"` picks CUDA when present, else the CPU; any other name is torch's."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo), else what the platform says."""
    import platform

    try:
        for line in open("/proc/cpuinfo", encoding="utf-8"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def cpu_features() -> list[str]:
    """The CPU features that decide which training settings are fastest: the bf16 matrix units (AMX on Intel,
    AVX-512 BF16 on AMD and Intel) and AVX-512 itself. A model name such as "AMD EPYC" does not tell them."""
    wanted = ("amx_bf16", "amx_tile", "avx512_bf16", "avx512f")
    try:
        for line in open("/proc/cpuinfo", encoding="utf-8"):
            if line.startswith("flags"):
                flags = set(line.split(":", 1)[1].split())
                return [flag for flag in wanted if flag in flags]
    except OSError:
        pass
    return []


def machine_key(device: torch.device) -> str:
    """What a speed measurement holds for: the GPU, or the CPU model, its relevant features and the thread
    count; with torch's version."""
    if device.type == "cuda":
        name = torch.cuda.get_device_name(device)
    else:
        name = f"{cpu_model()} [{' '.join(cpu_features())}] x{torch.get_num_threads()}"
    return f"{name}; torch {torch.__version__}"
