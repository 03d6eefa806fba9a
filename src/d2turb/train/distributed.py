"""DDP plumbing of the trainer: the process group, the sharded resumable sampler, collectives on small values and
the DistributedDataParallel wrapper. One process (``WORLD_SIZE`` 1) needs none of it: every helper is then a no-op."""

from __future__ import annotations

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DistributedSampler, Sampler

from d2turb.device import collective_device, distributed_env, resolve_device


class ResumableSampler(Sampler):
    """A DistributedSampler (shuffled by seed + epoch, rank's share) that can skip its first ``skip`` indices."""

    def __init__(self, dataset, world: int, rank: int, seed: int, shuffle: bool = True):
        self.inner = DistributedSampler(dataset, num_replicas=world, rank=rank, shuffle=shuffle, seed=seed)
        self.skip = 0

    def set_epoch(self, epoch: int, skip: int = 0) -> None:
        self.inner.set_epoch(epoch)
        self.skip = skip

    def __iter__(self):
        return iter(list(self.inner)[self.skip :])

    def __len__(self) -> int:
        return len(self.inner) - self.skip


def init_distributed(device_name: str) -> tuple[int, int, torch.device]:
    """Join the process group of a ``torchrun`` launch (nccl on CUDA, gloo on CPU; none for one process).

    Args:
        device_name: ``train.device`` (see :func:`d2turb.device.resolve_device`; ``LOCAL_RANK`` picks the GPU).

    Returns:
        (rank, world size, device) from :func:`d2turb.device.distributed_env`.
    """
    env = distributed_env()
    device = resolve_device(device_name, env.local_rank)
    if device.type == "cuda":
        torch.cuda.set_device(device)
    if env.world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo", rank=env.rank, world_size=env.world)
    return env.rank, env.world, device


def gather_objects(obj, world: int) -> list:
    """Every rank's ``obj`` (picklable), in rank order: ``[obj]`` for one process."""
    if world == 1:
        return [obj]
    out = [None] * world
    dist.all_gather_object(out, obj)
    return out


def all_reduce_values(values: torch.Tensor, op: dist.ReduceOp, world: int) -> torch.Tensor:
    """A small CPU tensor reduced elementwise over the ranks (e.g. MIN of finite flags, MAX of stop flags), on CPU."""
    if world == 1:
        return values
    reduced = values.to(collective_device())
    dist.all_reduce(reduced, op=op)
    return reduced.cpu()


def wrap_ddp(model: torch.nn.Module, device: torch.device, world: int) -> torch.nn.Module:
    """``model`` in DistributedDataParallel (gradients averaged over the ranks); ``model`` itself for one process."""
    if world == 1:
        return model
    return DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)


def shutdown(world: int) -> None:
    """Wait for every rank, then leave the process group."""
    if world > 1 and dist.is_initialized():
        dist.barrier()
        dist.destroy_process_group()
