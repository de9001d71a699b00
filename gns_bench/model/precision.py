"""Reduced precision: bf16 autocast (AMX on recent CPUs, tensor cores on CUDA) as an option.

Only the network runs in bf16; features, normalisation, integration and the loss stay in fp32, so
positions never round to bf16's 8-bit mantissa.
"""

from __future__ import annotations

from contextlib import AbstractContextManager, nullcontext

import torch

PRECISIONS = ("fp32", "bf16", "fp64")  # fp64: rollouts only, the caller casts the network (a reference on CPU)


def autocast(device: torch.device | str, precision: str) -> AbstractContextManager:
    if precision not in PRECISIONS:
        raise ValueError(f"unknown precision {precision!r}; expected one of {PRECISIONS}")
    if precision == "bf16":
        return torch.autocast(device_type=torch.device(device).type, dtype=torch.bfloat16)
    return nullcontext()
