"""Reduced precision: bf16 autocast (AMX on recent CPUs, tensor cores on CUDA) as an option.

Only the network runs in bf16; features, normalisation, integration and the loss stay in fp32, so
positions never round to bf16's 8-bit mantissa.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext

import torch
from torch import nn

PRECISIONS = ("fp32", "bf16", "fp64")  # fp64: rollouts only, the caller casts the network (a reference on CPU)


def autocast(device: torch.device | str, precision: str) -> AbstractContextManager:
    if precision not in PRECISIONS:
        raise ValueError(f"unknown precision {precision!r}; expected one of {PRECISIONS}")
    if precision == "bf16":
        return torch.autocast(device_type=torch.device(device).type, dtype=torch.bfloat16)
    return nullcontext()


def dtype_of(precision: str) -> torch.dtype:
    """The dtype positions and the network's parameters use: float64 for the fp64 reference, else float32."""
    return torch.float64 if precision == "fp64" else torch.float32


@contextmanager
def network_dtype(module: nn.Module, dtype: torch.dtype) -> Iterator[None]:
    """Run a module's parameters and buffers in `dtype` (float64 for the fp64 reference), then restore
    float32 (exact: the float32 values survive the round trip)."""
    if dtype == torch.float32:
        yield
        return
    module.to(dtype)
    try:
        yield
    finally:
        module.to(torch.float32)


def compiled_for_inference(simulator: nn.Module) -> nn.Module:
    """A copy of `simulator` whose network is compiled for rollouts (`eval.compile`): `torch.compile` with
    dynamic shapes (one compilation serves every particle and edge count) and inductor's freezing, which
    treats the fixed weights as constants (pre-packed for oneDNN on CPU, linear + ReLU fused). The caller's
    model is untouched: frozen weights would go stale if it trained on. On an AMD EPYC, 2 threads (WATERDROP-
    sized graph, 1,000 particles, 14.7k edges, the paper's model), a bf16 rollout step went from 43 to 31 ms
    after about 15 s of compiling; in fp32 it brought nothing (118 against 139 ms in the same bench run;
    `gns-bench bench` times both on the machine at hand). The baselines' networks compile the same way (their
    training compiles them too): CConv's BOXBATH step (1,032 particles, bf16) went from 97 to 70 ms after 14 s of
    compiling, the same outputs, on an AMD EPYC (CPU family 25, model 17), 2 threads; on WATER-3D-S its rollouts
    ran at 0.24 s a step compiled against about 0.7 s eager (the campaign's run, same machine). Their neighbour
    search and DPI-Net's rigid projection stay eager, as the GNS's graph building does."""
    import copy

    compiled = copy.deepcopy(simulator).eval()
    network = getattr(compiled, "network", None)
    if network is not None:
        network.compile(dynamic=True, options={"freezing": True})
    return compiled
