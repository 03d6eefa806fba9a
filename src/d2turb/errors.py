"""The user-facing error, and the rule for a batch of inputs with bad files in it (every readable input is
processed, one ``error:`` line per bad one, a closing summary, exit status 1; ``fail_fast`` stops at the first),
shared by the library's file jobs and the command line."""

from __future__ import annotations

import sys


class D2TurbError(ValueError):
    """A user-facing error: bad input, impossible parameters, missing weights.

    A ``ValueError``, so callers that already catch bad values catch it too. The CLI prints its message as
    one line (``error: ...``) and exits with status 2; library code raises it ``from`` the underlying
    exception so the cause stays in the traceback.

    Messages name parameters as a Python caller types them (``patch must be at least 16``). ``param`` says which
    parameter the message starts with; the command line puts the flag of that parameter in its place
    (``--patch must be at least 16``).
    """

    def __init__(self, *args, param: str | None = None):
        super().__init__(*args)
        self.param = param


def print_error(message: str) -> None:
    """``error: message`` on stderr in one line, above any progress bar."""
    message = " ".join(message.split())
    if "tqdm" in sys.modules:
        from tqdm import tqdm

        tqdm.write(f"error: {message}", file=sys.stderr)
    else:
        print(f"error: {message}", file=sys.stderr, flush=True)


class FileErrors:
    """Per-input failures of a batch job.

    ``record(exc)`` prints one ``error:`` line and goes on, or re-raises the error with ``fail_fast`` (and
    when there is a single input, whose error then is the job's one line). ``finish`` prints the
    summary and returns the exit status: 0 all done, 1 some inputs failed, 2 all failed.
    """

    def __init__(self, total: int, fail_fast: bool = False):
        self.total, self.fail_fast = total, fail_fast or total == 1
        self.failed: list[str] = []

    def record(self, exc: D2TurbError) -> None:
        if self.fail_fast:
            raise exc
        print_error(str(exc))
        self.failed.append(str(exc))

    def finish(self, command: str) -> int:
        return summary(command, self.total, len(self.failed))


def summary(command: str, total: int, failed: int) -> int:
    """The closing line of a batch with failed inputs, and the exit status (0 none, 1 some, 2 all failed)."""
    if not failed:
        return 0
    done = total - failed
    print(f"{command}: {done} of {total} inputs done, {failed} failed (see the error lines)", file=sys.stderr)
    return 1 if done else 2
