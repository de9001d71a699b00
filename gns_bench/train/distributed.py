"""Data parallelism through torch.distributed, for runs launched by torchrun.

torchrun sets RANK / WORLD_SIZE / MASTER_ADDR; this module turns them into a process group (gloo on
CPU, nccl on CUDA) and wraps the model in DistributedDataParallel. Without torchrun it is a no-op, so
the training loop is the same whatever launched it.
"""

from __future__ import annotations

import os
import weakref
from dataclasses import dataclass, field

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel


@dataclass
class ProcessGroup:
    rank: int = 0
    world_size: int = 1
    owns_group: bool = False
    _wrapped: list[weakref.ref] = field(default_factory=list, repr=False)

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def wrap(self, model: torch.nn.Module) -> torch.nn.Module:
        """`model` in DistributedDataParallel when there is more than one rank. Drop the wrapper (`del`)
        before `close()`."""
        if self.world_size == 1:
            return model
        device = next(model.parameters()).device
        wrapped = DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)
        self._wrapped.append(weakref.ref(wrapped))
        return wrapped

    def close(self) -> None:
        """Wait for every rank, then destroy the group.

        Every DistributedDataParallel wrapper from `wrap` must be gone first. Its reducer holds the gloo
        group, and a group whose last owner is a reducer freed after `destroy_process_group` is destroyed
        with the GIL held: its destructor joins a gloo worker thread that waits for the GIL, and the rank
        hangs for good. That hung a CI run; 2-rank teardowns in the old order hung within 8 to 19 cycles in each
        of 3 tries, and in this order ran 200 of 200 in each of 3.

        On gloo the wait is a `monitored_barrier` (send/recv), not `barrier`. A gloo `barrier` holds every
        collective still queued or in flight when it starts, among them DDP's last allreduce. That allreduce
        captured, with the thread-local state, the Python context torch stashes there for the length of
        backward. The gloo worker thread drops the barrier, and so the allreduce, only after `barrier()` has
        returned; on a loaded machine that came during interpreter shutdown, and its GIL request aborted the
        rank ("terminate called without an active exception"; a core showed ~AsyncBarrierWork ->
        ~AsyncAllreduceWork -> SafePyObject decref on the worker thread). With `barrier` this failed a
        clean-clone `.ci/run` and 2 of 76 looped teardowns while a training run shared the cores; with
        `monitored_barrier`, 120 of 120 passed under the same load.
        """
        if any(ref() is not None for ref in self._wrapped):
            raise RuntimeError("ProcessGroup.close(): a DistributedDataParallel wrapper from wrap() is still "
                               "alive; drop every reference to it (del model) first, or its teardown deadlocks")
        if self.owns_group and dist.is_initialized():
            if dist.get_backend() == "gloo":
                dist.monitored_barrier()
            else:
                dist.barrier()
            dist.destroy_process_group()
            self.owns_group = False


def launched_rank() -> int:
    """This process's rank as torchrun set it (0 when torchrun did not launch it), before any group exists."""
    return int(os.environ.get("RANK", "0"))


def from_environment(device: torch.device) -> ProcessGroup:
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if world_size == 1:
        return ProcessGroup()
    if not dist.is_initialized():
        backend = "nccl" if device.type == "cuda" else "gloo"
        dist.init_process_group(backend=backend)
        return ProcessGroup(dist.get_rank(), dist.get_world_size(), owns_group=True)
    return ProcessGroup(dist.get_rank(), dist.get_world_size())
