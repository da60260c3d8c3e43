"""torch.distributed set-up from torchrun's environment (RANK, WORLD_SIZE, LOCAL_RANK): DDP, samplers, sharding.

- The process group gets an explicit timeout (default 30 min): a collective that waits longer fails with an error
  naming the rank instead of hanging, and long phases (validation) are sharded so no rank waits for another's work.
- Under DDP on CUDA, BatchNorm becomes SyncBatchNorm (each GPU sees only one or two correlated windows, too few for
  batch statistics of its own). torch's SyncBatchNorm runs on GPUs only, so CPU (gloo) runs keep per-rank BatchNorm
  and copy rank 0's running statistics to every rank after each epoch (broadcast_buffers).
- EpochSampler yields (epoch, index) keys: the dataset seeds each window's augmentation from them, so a window's
  content is independent of DataLoader workers and of where a run was resumed.
"""

from __future__ import annotations

import datetime
import logging
import os
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import torch
from torch import distributed as dist
from torch import nn
from torch.utils.data import Dataset, DistributedSampler

from rafd.model.device import resolve_device

log = logging.getLogger(__name__)

DEFAULT_TIMEOUT_MINUTES = 30.0


@dataclass(frozen=True)
class DistContext:
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    local_world_size: int = 1
    device: torch.device = torch.device("cpu")

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        """Only rank 0 logs progress and writes checkpoints."""
        return self.rank == 0


def _env_int(name: str, default: int) -> int:
    value = os.environ.get(name)
    if value is None or value == "":
        return default
    try:
        return int(value)
    except ValueError as error:
        raise ValueError(f"environment variable {name}={value!r} is not an integer") from error


def init_distributed(device: str = "auto", timeout_minutes: float = DEFAULT_TIMEOUT_MINUTES) -> DistContext:
    """Join the process group when torchrun's WORLD_SIZE > 1; gloo on CPU, nccl on CUDA."""
    world_size = _env_int("WORLD_SIZE", 1)
    rank = _env_int("RANK", 0)
    local_rank = _env_int("LOCAL_RANK", 0)
    local_world_size = _env_int("LOCAL_WORLD_SIZE", world_size)
    resolved = resolve_device(device)
    if resolved.type == "cuda" and resolved.index is None:
        resolved = torch.device("cuda", local_rank)  # one GPU per process: torchrun's LOCAL_RANK picks it
    if resolved.type == "cuda":
        torch.cuda.set_device(resolved)
    if world_size > 1 and not dist.is_initialized():
        backend = "nccl" if resolved.type == "cuda" else "gloo"
        dist.init_process_group(
            backend=backend, rank=rank, world_size=world_size, timeout=datetime.timedelta(minutes=timeout_minutes)
        )
        log.info(
            "rank %d/%d joined the %s process group on %s (timeout %.0f min)",
            rank,
            world_size,
            backend,
            resolved,
            timeout_minutes,
        )
    return DistContext(rank, world_size, local_rank, local_world_size, resolved)


def cleanup_distributed() -> None:
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


def uses_sync_batchnorm(ctx: DistContext) -> bool:
    """SyncBatchNorm under DDP on CUDA (torch implements it for GPUs only)."""
    return ctx.enabled and ctx.device.type == "cuda"


def wrap_model(model: nn.Module, ctx: DistContext) -> nn.Module:
    """DDP around the model when distributed (SyncBatchNorm on CUDA), the model itself otherwise.

    find_unused_parameters stays off: every RaFD variant uses every parameter it builds (T = 1 builds no flow
    branch, and the flow loss keeps the flow branch in the graph even at weight 0), which
    tests/rafd/train/test_distributed.py checks for each benchmark variant.
    """
    if not ctx.enabled:
        return model
    sync = uses_sync_batchnorm(ctx)
    if sync:
        model = nn.SyncBatchNorm.convert_sync_batchnorm(model)
    device_ids = [ctx.device.index] if ctx.device.type == "cuda" else None
    # SyncBatchNorm keeps the running statistics equal on every rank; plain BN gets rank 0's each forward.
    return nn.parallel.DistributedDataParallel(
        model, device_ids=device_ids, broadcast_buffers=not sync, find_unused_parameters=False
    )


def unwrap_model(model: nn.Module) -> nn.Module:
    return model.module if isinstance(model, nn.parallel.DistributedDataParallel) else model


class EpochSampler(DistributedSampler):
    """DistributedSampler that yields (epoch, index) keys instead of indices (see the module docstring)."""

    def __iter__(self) -> Iterator[tuple[int, int]]:
        epoch = self.epoch
        return ((epoch, int(index)) for index in super().__iter__())


def make_sampler(dataset: Dataset, ctx: DistContext, seed: int, shuffle: bool = True) -> EpochSampler:
    """Seeded per-epoch shuffling (set_epoch); the same code path with one or many processes."""
    return EpochSampler(
        dataset, num_replicas=ctx.world_size, rank=ctx.rank, shuffle=shuffle, seed=seed, drop_last=False
    )


def shard_indices(count: int, ctx: DistContext) -> list[int]:
    """This rank's share of `count` items (every item exactly once over all ranks; no padding)."""
    return list(range(ctx.rank, count, ctx.world_size))


def gather_objects(items: list[Any], ctx: DistContext) -> list[Any]:
    """Concatenate every rank's list (in rank order) on every rank; the list itself without a process group."""
    if not ctx.enabled:
        return list(items)
    gathered: list[list[Any] | None] = [None] * ctx.world_size
    dist.all_gather_object(gathered, items)
    return [item for part in gathered for item in (part or [])]


def all_reduce_mean(value: torch.Tensor, ctx: DistContext) -> torch.Tensor:
    """Average a tensor over ranks (for logging); identity without a process group."""
    if not ctx.enabled:
        return value
    value = value.detach().clone()
    dist.all_reduce(value, op=dist.ReduceOp.SUM)
    return value / ctx.world_size


def broadcast_buffers(model: nn.Module, ctx: DistContext) -> None:
    """Copy rank 0's buffers (BatchNorm running stats) to every rank, so every rank holds the same model."""
    if not ctx.enabled:
        return
    for buffer in unwrap_model(model).buffers():
        dist.broadcast(buffer.data, src=0)


def barrier(ctx: DistContext) -> None:
    if ctx.enabled:
        dist.barrier()
