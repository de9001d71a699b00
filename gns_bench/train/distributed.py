"""Data parallelism through torch.distributed, for runs launched by torchrun.

torchrun sets RANK / WORLD_SIZE / MASTER_ADDR; this module turns them into a process group (gloo on
CPU, nccl on CUDA) and wraps the model in DistributedDataParallel. Without torchrun it is a no-op, so
the training loop is the same whatever launched it.
"""

from __future__ import annotations

import itertools
import os
from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch.distributed.elastic.utils.store import barrier as store_barrier
from torch.nn.parallel import DistributedDataParallel

CLOSE_TIMEOUT_S = 600.0  # how long a finished rank waits for the slowest one (rank 0 writes the checkpoint)
_closes = itertools.count()  # every rank closes the same groups in the same order, so the counts agree


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
        """Leave the group once every rank is done with it.

        The last meeting goes through the launcher's key-value store, not a gloo or nccl barrier. A gloo
        barrier here hung once in about 60 runs: rank 0 had finished and exited, rank 1 slept on. The
        likely cause is the rank that leaves a collective first closing its sockets before its peer has
        read the last message. The store lives in torchrun's agent, outlives the workers, and times out
        with the missing ranks named.
        """
        if self.owns_group and dist.is_initialized():
            attempt = os.environ.get("TORCHELASTIC_RESTART_COUNT", "0")
            store_barrier(dist.distributed_c10d._get_default_store(), self.world_size,
                          key_prefix=f"gns_bench/close/{attempt}/{next(_closes)}",
                          barrier_timeout=CLOSE_TIMEOUT_S, rank=self.rank)
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
