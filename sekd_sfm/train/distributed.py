"""Device selection and data parallelism over processes started by ``torchrun``.

One process per device: ``torchrun --nproc_per_node N -m sekd_sfm.cli.main evolve ...``
sets RANK / WORLD_SIZE / LOCAL_RANK; gloo joins CPU processes, nccl GPU ones. Rank 0
writes every file; the others compute their share and wait at barriers.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field

import torch
import torch.distributed as dist
from torch import nn

from ..runtime import resolve_device, usable_cores


@dataclass(frozen=True)
class Context:
    """Where this process runs: its rank among ``world`` processes and its device."""

    rank: int = 0
    world: int = 1
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))

    @property
    def main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world > 1


def setup(device: str = "auto", num_threads: int = 0) -> Context:
    """Join the process group when launched by torchrun; pick the device and CPU threads."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank, local_rank = int(os.environ.get("RANK", "0")), int(os.environ.get("LOCAL_RANK", "0"))
    try:
        chosen = resolve_device(device)
    except ValueError as exc:
        from ..errors import SekdError
        raise SekdError(str(exc)) from exc
    if chosen.type == "cuda":
        chosen = torch.device("cuda", local_rank % torch.cuda.device_count())
        torch.cuda.set_device(chosen)
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if chosen.type == "cuda" else "gloo")
    cores = usable_cores()
    # Processes share the cores: each gets its slice unless the config fixes the count.
    torch.set_num_threads(num_threads or max(1, cores // world))
    return Context(rank, world, chosen)


def teardown() -> None:
    if dist.is_initialized():
        dist.destroy_process_group()


def barrier(ctx: Context) -> None:
    if ctx.distributed:
        dist.barrier()


def gather_objects(ctx: Context, item: object) -> list:
    """Every process's ``item``, in rank order, on every process."""
    if not ctx.distributed:
        return [item]
    items = [None] * ctx.world
    dist.all_gather_object(items, item)
    return items


def sum_across(ctx: Context, values: torch.Tensor) -> torch.Tensor:
    """Element-wise sum of a float tensor over processes (a copy on the CPU)."""
    values = values.detach().double().clone()
    if ctx.distributed:
        on_device = values.to(ctx.device) if ctx.device.type == "cuda" else values
        dist.all_reduce(on_device)
        values = on_device.cpu()
    return values


def shard(ctx: Context, items: list) -> list:
    """This process's share of ``items`` (every world-th, starting at its rank)."""
    return items[ctx.rank::ctx.world]


def wrap(module: nn.Module, ctx: Context) -> nn.Module:
    """DistributedDataParallel around ``module`` when there are several processes."""
    if not ctx.distributed:
        return module
    ids = [ctx.device.index] if ctx.device.type == "cuda" else None
    return nn.parallel.DistributedDataParallel(module, device_ids=ids)


def sync_buffers(ctx: Context, module: nn.Module) -> None:
    """Copy rank 0's buffers to every process.

    DistributedDataParallel broadcasts BatchNorm running statistics before each forward, so
    after the last one every process holds its own; labelling (eval mode) must use rank 0's.
    """
    if ctx.distributed:
        for buffer in module.buffers():
            dist.broadcast(buffer.data, src=0)


def check_in_sync(ctx: Context, module: nn.Module) -> float:
    """Raise if the processes' copies of ``module`` differ (DistributedDataParallel must keep them equal).

    Returns the order-sensitive checksum of the parameters and buffers.
    """
    values = [t.detach().double().flatten() for t in module.state_dict().values() if t.is_floating_point()]
    flat = torch.cat(values).cpu()
    checksum = float((flat * torch.linspace(1.0, 2.0, len(flat), dtype=torch.float64)).sum())
    sums = gather_objects(ctx, checksum)
    if any(s != sums[0] for s in sums):
        raise RuntimeError(f"model copies diverged across processes: checksums {sums}")
    return checksum
