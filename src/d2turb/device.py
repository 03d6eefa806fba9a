"""The one device resolver and the one reader of torchrun's environment: every command, the restorer, the trainer
and the dataset generator use them."""

from __future__ import annotations

import contextlib
import ctypes
import os
import threading
from dataclasses import dataclass

import torch
import torch.distributed as dist

from d2turb.defaults import DEVICE_HELP
from d2turb.errors import D2TurbError


def resolve_device(name: str | torch.device | None = "auto", local_rank: int = 0) -> torch.device:
    """A device name → ``torch.device``, refusing what this machine cannot run in one line.

    Args:
        name: ``"auto"`` (or None: CUDA when available, else CPU), ``"cpu"``, ``"cuda"`` or ``"cuda:N"``.
        local_rank: process index on this machine (``LOCAL_RANK`` under torchrun); ``auto``/``cuda`` without
            an index pick GPU ``local_rank % device_count``.

    Returns:
        The device.

    Raises:
        D2TurbError: not a device name, a device type other than cpu/cuda, CUDA requested on a machine
        (or torch build) without it, or a GPU index that does not exist.
    """
    text = "auto" if name is None else str(name).strip().lower()
    if text == "auto":
        text = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        device = torch.device(text)
    except (RuntimeError, ValueError) as exc:
        raise D2TurbError(f"device {str(name)!r} is not a device name (use {DEVICE_HELP})") from exc
    if device.type == "cpu":
        return torch.device("cpu")
    if device.type != "cuda":
        raise D2TurbError(f"device {str(name)!r} is not supported (use {DEVICE_HELP})")
    if not torch.cuda.is_available():
        why = "this torch build has no CUDA support" if torch.version.cuda is None else "no GPU is visible"
        raise D2TurbError(f"device {str(name)!r} requested but CUDA is not available ({why}); use --device cpu")
    count = torch.cuda.device_count()
    index = local_rank % count if device.index is None else device.index
    if not 0 <= index < count:
        raise D2TurbError(f"device {str(name)!r}: this machine has {count} GPU(s), cuda:0 to cuda:{count - 1}")
    return torch.device("cuda", index)


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one, else all)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


_M_ARENA_MAX = -8  # glibc's mallopt parameter (malloc.h)


def limit_malloc_arenas(arenas: int = 2) -> bool:
    """At most ``arenas`` glibc malloc arenas for the threads this process starts from now on (glibc only; elsewhere
    a no-op returning False), as ``MALLOC_ARENA_MAX`` would. Each thread that allocates gets an arena of its own by
    default, and frame-sized blocks freed in one stay held there: clip restoration's threads (deblur, writer,
    encoder, OpenCV's pool) then raise the 1080p peak by about 75 MB (benchmarks/RESULTS.md, issue 35)."""
    try:
        return bool(ctypes.CDLL(None).mallopt(_M_ARENA_MAX, int(arenas)))
    except (OSError, AttributeError):
        return False


@dataclass(frozen=True)
class DistributedEnv:
    """This process's place in a ``torchrun`` launch; the defaults are a single process."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0


def _env_int(name: str, default: int) -> int:
    text = os.environ.get(name)
    if text is None:
        return default
    try:
        return int(text)
    except ValueError as exc:
        raise D2TurbError(f"environment variable {name} must be an integer, got {text!r}") from exc


def distributed_env() -> DistributedEnv:
    """torchrun's ``RANK``, ``WORLD_SIZE`` and ``LOCAL_RANK`` (absent: one process).

    Returns:
        The environment; ``local_rank`` defaults to ``rank`` (processes started by hand on one machine).

    Raises:
        D2TurbError: a value that is not an integer, ``WORLD_SIZE`` < 1 or ``RANK`` outside [0, WORLD_SIZE).
    """
    world, rank = _env_int("WORLD_SIZE", 1), _env_int("RANK", 0)
    local_rank = _env_int("LOCAL_RANK", rank)
    if world < 1 or not 0 <= rank < world:
        raise D2TurbError(f"bad distributed environment: RANK={rank} WORLD_SIZE={world}")
    return DistributedEnv(rank, world, local_rank)


def collective_device() -> torch.device:
    """Where the tensors of a ``torch.distributed`` collective must live: the current GPU for nccl, else the CPU."""
    if dist.get_backend() == "nccl":
        return torch.device("cuda", torch.cuda.current_device())
    return torch.device("cpu")


_THREADS_LOCK = threading.RLock()  # re-entrant: a deblur inside the blind decision nests the block


@contextlib.contextmanager
def one_torch_thread(device: torch.device | None = None):
    """Run the block on one torch intra-op thread (on CPU; a GPU device runs it as it is): the count is lowered for
    the block and restored on the way out, under a lock so that two threads never save and restore each other's
    value. Used where a result must not depend on the thread count (the PSFs' PCA: MKL splits long inner
    dimensions by thread count, sim/psf.py) and where a second thread only adds wake-ups (the clip room's physical
    deblurs, a few FFTs beside the registration: 13 % less CPU on a 48-frame 256² clip, benchmarks/RESULTS.md)."""
    if device is not None and torch.device(device).type != "cpu":
        yield
        return
    with _THREADS_LOCK:
        threads = torch.get_num_threads()
        if threads == 1:
            yield
            return
        torch.set_num_threads(1)
        try:
            yield
        finally:
            torch.set_num_threads(threads)
