"""When a training run stops: at the configured total, after the steps one ``fit`` call may take, when the time
budget is spent or on SIGTERM; under DDP every rank stops at the same step."""

from __future__ import annotations

import contextlib
import signal
import time
from collections.abc import Iterator

import torch
import torch.distributed as dist

from d2turb.train.distributed import all_reduce_values


class StopConditions:
    """Why to stop: None, ``done``, ``max_steps``, ``max_minutes`` or ``signal``.

    Args:
        total: the run's total number of iterations.
        max_minutes: the time budget (None: none), counted from ``clock0_s``.
        clock0_s: ``time.monotonic()`` when the run started.
        world: the number of processes (their time-budget and signal flags are combined: any one stops all).
    """

    def __init__(self, total: int, max_minutes: float | None, clock0_s: float, world: int) -> None:
        self.total, self.max_minutes, self.clock0_s, self.world = total, max_minutes, clock0_s, world
        self.requested = False  # set by a SIGTERM (or by request())
        self.handles_signal = False

    def request(self, *_args) -> None:
        """Stop after the current step (the SIGTERM handler)."""
        self.requested = True

    @contextlib.contextmanager
    def sigterm_handled(self, enabled: bool) -> Iterator[None]:
        """With ``enabled`` (main thread only), SIGTERM calls :meth:`request` inside the block; the previous handler
        comes back afterwards."""
        self.handles_signal = enabled
        previous = signal.signal(signal.SIGTERM, self.request) if enabled else None
        try:
            yield
        finally:
            if previous is not None:
                signal.signal(signal.SIGTERM, previous)

    def reason(self, iteration: int, stop: int, after_step: bool = True) -> str | None:
        """Why to stop at ``iteration`` when this ``fit`` call stops at ``stop`` (a collective with a time budget or
        a handled signal: every rank calls it). The time budget and a signal are looked at only ``after_step``, so
        every call of ``fit`` makes progress."""
        if not after_step:
            return "done" if iteration >= self.total else ("max_steps" if iteration >= stop else None)
        budget = self.max_minutes
        spent = budget is not None and time.monotonic() - self.clock0_s >= 60.0 * budget
        flags = torch.tensor([float(spent), float(self.requested)])
        if budget is not None or self.handles_signal:
            flags = all_reduce_values(flags, dist.ReduceOp.MAX, self.world)
        if iteration >= self.total:
            return "done"
        if flags[1] > 0:
            return "signal"
        if flags[0] > 0:
            return "max_minutes"
        return "max_steps" if iteration >= stop else None
