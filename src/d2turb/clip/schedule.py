"""What runs when, and in which thread, in the clip room: the order of the stages over a clip (:func:`outputs`: read,
register round by round, emit as soon as a window is ready, release) and the threads that overlap them
(:func:`worker`, :func:`in_order`: one job in flight, results in order). Threads only change when a stage runs, never
what it computes: a restorer run with ``threaded=False`` gives the same outputs to the bit (tests/test_clip.py)."""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import math
from collections.abc import Callable, Iterable, Iterator

from d2turb.clip.stages import output_job, register
from d2turb.clip.state import ClipState


@contextlib.contextmanager
def worker(name: str, enabled: bool):
    """A thread of its own (``submit(call)`` → a Future), or None when not ``enabled`` (the caller runs it)."""
    if not enabled:
        yield None
        return
    pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix=name)
    try:
        yield pool
    finally:  # a stream closed early: drop what is queued, finish what runs
        pool.shutdown(wait=True, cancel_futures=True)


def in_order(jobs: Iterable, depth: int = 1) -> Iterator:
    """The results of ``jobs`` (Futures, or values), in order, with ``depth`` more in flight than the one waited for;
    a result that is ready (a value, a finished Future) is passed on at once, without waiting for the next job to be
    made (an output is not held back by the next one's registration, which on a stream waits for the next input
    frame: one frame interval of latency less). What is still queued when the caller stops is cancelled."""
    pending: collections.deque = collections.deque()
    try:
        for job in jobs:
            pending.append(job)
            while pending and (len(pending) > depth or _ready(pending[0])):
                yield _result(pending.popleft())
        while pending:
            yield _result(pending.popleft())
    finally:
        for job in pending:
            if isinstance(job, concurrent.futures.Future):
                job.cancel()


def _ready(job) -> bool:
    return not isinstance(job, concurrent.futures.Future) or job.done()


def _result(job):
    return job.result() if isinstance(job, concurrent.futures.Future) else job


def run_in(pool) -> Callable:
    """``submit(call)``: in ``pool`` (a Future), or now when ``pool`` is None."""
    return (lambda call: call()) if pool is None else pool.submit


def outputs(state: ClipState, frames: Iterable, fallback: bool, fuse_pool=None, prepare_pool=None) -> Iterator:
    """Read, register and fuse: the outputs in order (with ``fuse_pool``, Futures of them). Frames are read only
    as far as the windows need, each round runs no further ahead than the next round (or output) needs, and what
    nothing left reads is released: memory holds about 2·temporal·passes frames whatever the clip's length."""
    source = iter(frames)
    passes, done = state.passes, state.done
    prepare = run_in(prepare_pool)
    share = None if prepare_pool is None else prepare_pool.submit
    while state.emitted < (state.length if state.length is not None else math.inf):
        progressed = False
        if state.length is None:
            item = next(source, None)
            if item is None:
                state.end()
            else:
                state.hold(item)
            progressed = True
        total = state.length if state.length is not None else done[0]
        for k in range(1, passes + 1):  # round k of frame i needs round k-1 of W(i)
            # no further ahead than the next round (or output) needs: once the clip's end is read, every window
            # is ready, and running ahead would hold a window more of unwarped frames and flows (1080p: 0.2 GB)
            need = state.window_end(done[k + 1] if k < passes else state.emitted, k)
            while done[k] < min(total, need) and state.window_ready(done[k], k - 1):
                register(state, done[k], k, prepare)
                done[k] += 1
                progressed = True
        while state.emitted < done[passes] and state.window_ready(state.emitted, passes):
            job = output_job(state, state.emitted, fallback, share)
            yield job() if fuse_pool is None else fuse_pool.submit(job)
            state.emitted += 1
            progressed = True
        state.release()
        if not progressed and state.length is not None:
            raise RuntimeError("clip restoration made no progress")  # pragma: no cover - a logic error
