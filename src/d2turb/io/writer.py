"""The background writer of the batch jobs: outputs are encoded and written while the next inputs are read and
computed."""

from __future__ import annotations

import contextlib
import queue
import threading
from collections.abc import Callable

import torch

from d2turb.device import usable_cores


class BackgroundWriter:
    """Run write jobs in background threads, so a batch command reads and computes while earlier outputs
    are encoded and written. Jobs should write atomically (``write_image`` etc.) and convert tensors with
    numpy (:func:`float_array`): a torch operator in another thread starts an OpenMP team of its own.

    ``submit`` blocks while ``max_pending`` jobs wait (bounded memory). The first error of a job is raised
    in the caller at the next ``submit`` or at ``close``; later jobs are dropped. Used as a context manager,
    an exception in the block (Ctrl-C) drops the jobs not started and waits for the running ones.

    The writes are *phased* when the computation runs on the CPU with a torch thread on every core: then
    :meth:`before_compute` waits for the queued jobs, which meanwhile run one thread per core, because the
    computation's OpenMP threads lose more time to a writer beside them (spinning at barriers while it holds
    a core) than the writes take on all cores in between (benchmarks/bench_cli_sim.py). The next inputs are
    still read while the writers work. Otherwise (a GPU, or a core left free) the writes overlap.

    Args:
        max_pending: queue length.
        compute_device: device of the computation the writes alternate with (None: no computation).
        threads: writer threads (the PNG encoders release the GIL); default: one per core when phased, else
            one per two cores beyond the first; at most 4.
    """

    def __init__(self, max_pending: int = 16, compute_device=None, threads: int | None = None):
        cores = usable_cores()
        self.phased = (
            compute_device is not None
            and torch.device(compute_device).type == "cpu"
            and torch.get_num_threads() >= cores
        )
        if threads is None:
            threads = min(4, cores if self.phased else (cores - 1) // 2)
        self._queue: queue.Queue = queue.Queue(maxsize=max(1, max_pending))
        self._error: BaseException | None = None
        self._lock = threading.Lock()
        self._threads = [
            threading.Thread(target=self._work, name=f"d2turb-writer-{i}", daemon=True) for i in range(max(1, threads))
        ]
        for t in self._threads:
            t.start()
        self._closed = False

    def _work(self) -> None:
        while True:
            job = self._queue.get()
            try:
                if job is None:
                    return
                if self._error is None:
                    fn, args, kwargs = job
                    fn(*args, **kwargs)
            except BaseException as exc:  # handed to the caller's thread
                with self._lock:
                    if self._error is None:
                        self._error = exc
            finally:
                self._queue.task_done()

    def _raise_error(self) -> None:
        if self._error is not None:  # sticky: the jobs after a failed one stay dropped
            raise self._error

    def submit(self, fn: Callable, *args, **kwargs) -> None:
        """Queue ``fn(*args, **kwargs)``; raises the error of an earlier job, if any."""
        if self._closed:
            raise RuntimeError("BackgroundWriter is closed")
        self._raise_error()
        self._queue.put((fn, args, kwargs))

    def before_compute(self) -> None:
        """When phased, block until the queued jobs are done (raising the error of one, if any)."""
        if self.phased:
            self._queue.join()
            self._raise_error()

    def close(self, cancel: bool = False) -> None:
        """Finish (or, with ``cancel``, drop) the queued jobs, stop the threads, raise a job's error."""
        if self._closed:
            return
        self._closed = True
        if cancel:
            while True:
                try:
                    self._queue.get_nowait()
                except queue.Empty:
                    break
                self._queue.task_done()
        for _ in self._threads:
            self._queue.put(None)
        for t in self._threads:
            t.join()
        self._raise_error()

    def __enter__(self) -> BackgroundWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:  # the block's exception wins; a writer error would only hide it
            with contextlib.suppress(Exception):
                self.close(cancel=True)
