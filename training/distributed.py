"""Device choice and data-parallel plumbing (torchrun / DDP), inert in a single process.

Under ``torchrun --nproc_per_node G -m tactile_deploy.training train --config C.json`` every rank reads RANK,
WORLD_SIZE and LOCAL_RANK, makes or reads its own data shard, and trains a DDP-wrapped copy;
rank 0 alone writes files. In a plain process everything here is a no-op.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import torch

from tactile_deploy.training.errors import UsageError


@dataclass(frozen=True)
class Dist:
    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def active(self) -> bool:
        return self.world > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def resolve_device(name: str, local_rank: int = 0) -> torch.device:
    """'cpu', 'cuda', 'cuda:N' or 'auto' (CUDA when available); under torchrun 'cuda' means the
    rank's own GPU."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise UsageError(f"device {name!r} asked for but CUDA is not available; use device 'cpu' "
                             "(--device cpu, or 'device' in the config)")
        if name == "cuda":
            name = f"cuda:{local_rank}"
    elif name != "cpu":
        raise UsageError(f"device must be 'cpu', 'cuda', 'cuda:N' or 'auto', got {name!r}")
    return torch.device(name)


def init(device_name: str) -> tuple[Dist, torch.device]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Dist(), resolve_device(device_name)
    dist = Dist(int(os.environ["RANK"]), world, int(os.environ.get("LOCAL_RANK", "0")))
    device = resolve_device(device_name, dist.local_rank)
    if device.type == "cuda":
        torch.cuda.set_device(device)
    if not torch.distributed.is_initialized():
        torch.distributed.init_process_group(backend="nccl" if device.type == "cuda" else "gloo")
    return dist, device


def wrap(module: torch.nn.Module, dist: Dist, device: torch.device) -> torch.nn.Module:
    if not dist.active:
        return module
    from torch.nn.parallel import DistributedDataParallel

    return DistributedDataParallel(module, device_ids=[device.index] if device.type == "cuda" else None)


def reduce_sum(values: np.ndarray, dist: Dist, device: torch.device) -> np.ndarray:
    """Sum of ``values`` (float64 array) over ranks."""
    if not dist.active:
        return np.asarray(values, np.float64)
    t = torch.as_tensor(np.asarray(values, np.float64), device=device)
    torch.distributed.all_reduce(t)
    return t.cpu().numpy()


def reduce_min(value: int, dist: Dist, device: torch.device) -> int:
    if not dist.active:
        return int(value)
    t = torch.tensor([value], device=device, dtype=torch.int64)
    torch.distributed.all_reduce(t, op=torch.distributed.ReduceOp.MIN)
    return int(t.item())


def barrier(dist: Dist) -> None:
    if dist.active:
        torch.distributed.barrier()
