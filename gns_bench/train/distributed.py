"""Data parallelism through torch.distributed, for runs launched by torchrun.

torchrun sets RANK / WORLD_SIZE / MASTER_ADDR; this module turns them into a process group (gloo on
CPU, nccl on CUDA) and wraps the model in DistributedDataParallel. Without torchrun it is a no-op, so
the training loop is the same whatever launched it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel


@dataclass
class ProcessGroup:
    rank: int = 0
    world_size: int = 1
    owns_group: bool = False

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def wrap(self, model: torch.nn.Module) -> torch.nn.Module:
        if self.world_size == 1:
            return model
        device = next(model.parameters()).device
        return DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)

    def close(self) -> None:
        if self.owns_group and dist.is_initialized():
            dist.barrier()
            dist.destroy_process_group()
            self.owns_group = False


def from_environment(device: torch.device) -> ProcessGroup:
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if world_size == 1:
        return ProcessGroup()
    if not dist.is_initialized():
        backend = "nccl" if device.type == "cuda" else "gloo"
        dist.init_process_group(backend=backend)
        return ProcessGroup(dist.get_rank(), dist.get_world_size(), owns_group=True)
    return ProcessGroup(dist.get_rank(), dist.get_world_size())
