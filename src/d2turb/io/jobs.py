"""The skeleton of the batch jobs over input files (``d2turb simulate``, ``d2turb restore``): every readable input
is processed, a bad one is reported in one ``error:`` line and skipped (:class:`~d2turb.errors.FileErrors`), the
outputs are written in the background (:class:`~d2turb.io.writer.BackgroundWriter`) and a progress bar runs over
the inputs; the job ends with the summary line and exit status of ``FileErrors``. Their options are one value:
:class:`JobOptions`, and a subclass of it per job."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

from tqdm import tqdm

from d2turb.defaults import DEFAULT_DEVICE, DEFAULT_PNG_LEVEL
from d2turb.errors import D2TurbError, FileErrors
from d2turb.io.writer import BackgroundWriter


@dataclasses.dataclass(frozen=True)
class JobOptions:
    """What every file job takes beside its inputs; each job's options are a subclass
    (:class:`~d2turb.restore.files.RestoreOptions`, :class:`~d2turb.restore.clip_build.ClipOptions`,
    :class:`~d2turb.data.simulate.SimulateOptions`), and its command builds them from its parsed arguments
    (:meth:`from_args`).

    Args:
        device: where the job computes (``auto``, ``cpu``, ``cuda``, ``cuda:N``).
        save_flow: also write the flow of each output (its direction and unit are the job's).
        png_level: PNG compression level, 0-9.
        fail_fast: raise the first input's error instead of reporting it and going on.
    """

    device: str = DEFAULT_DEVICE
    save_flow: bool = False
    png_level: int = DEFAULT_PNG_LEVEL
    fail_fast: bool = False

    @classmethod
    def of(cls, options: JobOptions | None = None, /, **overrides):
        """``options`` (None: the defaults) as this class, with ``overrides`` in place of its fields: the keyword
        form of a job's call (``restore_files(paths, out, tile=256)``). The fields ``options`` shares with this
        class are kept; an unknown keyword raises TypeError, as a function's does."""
        names = {f.name for f in dataclasses.fields(cls)}
        values = {} if options is None else {f.name: getattr(options, f.name) for f in dataclasses.fields(options)}
        return cls(**{**{k: v for k, v in values.items() if k in names}, **overrides})

    @classmethod
    def from_args(cls, args, **values):
        """These options from a command's parsed arguments: each field from the argument of its name (when the
        command has one), ``values`` in place of those."""
        given = {f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if hasattr(args, f.name)}
        return cls(**{**given, **values})


def named_error(path: Path, exc: D2TurbError) -> D2TurbError:
    """``exc`` with its message starting with ``path`` (as it is when it already does)."""
    return exc if str(exc).startswith(str(path)) else D2TurbError(f"{path}: {exc}")


class FileJob:
    """A batch job over ``total`` input files, used as a context manager around its loop::

        with FileJob("restore", len(paths), fail_fast, max_pending=4, compute_device=device) as job:
            for path, result in job.each(paths, work, named=True, desc="restore", unit="img"):
                job.submit(save, out, path.stem, result)
        return job.finish()

    Leaving the block waits for the writes (an exception in it, Ctrl-C, drops the writes not started: see
    :class:`~d2turb.io.writer.BackgroundWriter`).

    Args:
        command: the name in the summary line (``COMMAND: 2 of 3 inputs done, ...``).
        total: the number of inputs.
        fail_fast: raise the first input's error instead of reporting it and going on (always so for one input).
        max_pending, compute_device: of the background writer.
    """

    def __init__(self, command: str, total: int, fail_fast: bool = False, *, max_pending: int, compute_device=None):
        self.command = command
        self.errors = FileErrors(total, fail_fast)
        self._writer_args = {"max_pending": max_pending, "compute_device": compute_device}
        self.writer: BackgroundWriter | None = None  # started on entering the block

    def __enter__(self) -> FileJob:
        self.writer = BackgroundWriter(**self._writer_args).__enter__()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.writer.__exit__(exc_type, exc, tb)

    def record(self, exc: D2TurbError, path: Path | None = None) -> None:
        """Report a failed input in one ``error:`` line (naming ``path``, when given), or raise its error."""
        self.errors.record(exc if path is None else named_error(path, exc))

    def each(
        self,
        items: Iterable,
        work: Callable,
        *,
        named: bool = False,
        desc: str | None = None,
        unit: str = "file",
    ) -> Iterator[tuple]:
        """``(item, work(item))`` for each of ``items`` in turn whose work succeeds; the D2TurbError of one is
        recorded (:meth:`record`) and the next goes on.

        Args:
            named: the items are the input paths, and each error names its input.
            desc, unit: a progress bar over the items (shown for two or more); None: no bar.
        """
        if desc is not None:
            items = list(items)
            items = tqdm(items, desc=desc, unit=unit, disable=len(items) < 2)
        for item in items:
            try:
                result = work(item)
            except D2TurbError as exc:
                self.record(exc, item if named else None)
                continue
            yield item, result

    def submit(self, fn: Callable, *args, **kwargs) -> None:
        """Write in the background: ``fn(*args, **kwargs)`` (:meth:`BackgroundWriter.submit`)."""
        self.writer.submit(fn, *args, **kwargs)

    def before_compute(self) -> None:
        """Call before each computation (:meth:`BackgroundWriter.before_compute`)."""
        self.writer.before_compute()

    def finish(self) -> int:
        """The summary line of the failed inputs, and the exit status: 0 all done, 1 some failed, 2 all failed."""
        return self.errors.finish(self.command)
