"""Progress of a run, shown and written by rank 0: ``status.json`` (state, progress, speed, ETA, last loss and
validation; read by ``d2turb train --status``), ``log.jsonl`` (one JSON record per logged step or validation),
``config.yaml`` (the run's config) and the progress bar."""

from __future__ import annotations

import json
import math
import os
import socket
import sys
import time
from pathlib import Path

from d2turb.errors import D2TurbError
from d2turb.io import write_json, write_text

STATUS = "status.json"
LOG = "log.jsonl"
CONFIG = "config.yaml"


def read_status(run_dir: str | os.PathLike) -> dict:
    """The ``status.json`` of a run folder, with ``alive`` added (True/False for a running process on this host,
    None when it cannot be told)."""
    path = Path(run_dir) / STATUS
    if not path.is_file():
        raise D2TurbError(f"{run_dir}: no {STATUS} (not a run folder, or training has not started yet)")
    try:
        status = json.loads(path.read_text())
    except ValueError as exc:
        raise D2TurbError(f"{path}: unreadable") from exc
    status["alive"] = None
    if status.get("state") == "running" and status.get("host") == socket.gethostname():
        try:
            os.kill(int(status["pid"]), 0)
            status["alive"] = True
        except ProcessLookupError:
            status["alive"] = False
        except (PermissionError, KeyError, ValueError, TypeError):
            pass
    return status


class RunProgress:
    """The progress files of ``run_dir`` and the progress bar; every call is a no-op unless ``enabled`` (rank 0).

    Args:
        run_dir: the run folder.
        enabled: write the files (rank 0 only).
        clock0_s: ``time.monotonic()`` when the run started (``elapsed_s`` counts from there).
    """

    def __init__(self, run_dir: Path, enabled: bool, clock0_s: float) -> None:
        self.run_dir, self.enabled, self.clock0_s = Path(run_dir), enabled, clock0_s
        self.fit_clock_s: float | None = None  # speed and ETA count from the start of the current fit
        self.fit_start_iteration = 0
        self.written_s = -math.inf  # when status.json was last written

    def start_fit(self, iteration: int, config: dict) -> None:
        """A call of ``fit`` starts at ``iteration``: write ``config.yaml``; the speed is measured from here."""
        if self.enabled:
            import yaml

            self.run_dir.mkdir(parents=True, exist_ok=True)
            write_text(self.run_dir / CONFIG, yaml.safe_dump(config, sort_keys=False))
        self.fit_clock_s, self.fit_start_iteration = time.monotonic(), iteration

    def progress_bar(self, total: int, initial: int, show: bool):
        """A tqdm bar on stderr (None unless ``show`` and ``enabled``)."""
        if not (show and self.enabled):
            return None
        from tqdm import tqdm

        return tqdm(total=total, initial=initial, desc="train", dynamic_ncols=True, file=sys.stderr)

    def status_due(self, interval_s: float = 10.0) -> bool:
        """Whether ``status.json`` is older than ``interval_s``."""
        return time.monotonic() - self.written_s > interval_s

    def write_status(
        self,
        state: str,
        *,
        iteration: int,
        total: int,
        max_minutes: float | None,
        loss: float | None,
        val: dict | None,
        checkpoint_iteration: int | None,
        **extra,
    ) -> None:
        """Write ``status.json``: ``state`` (running, finished, stopped, failed), pid, host, progress, ``it_per_s``,
        ``eta_s``, ``elapsed_s`` (s), the last loss and validation, the iteration of the last checkpoint and
        ``extra`` (``reason``, ``error``)."""
        if not self.enabled:
            return
        now = time.monotonic()
        run_s = now - self.fit_clock_s if self.fit_clock_s is not None else 0.0
        done = iteration - self.fit_start_iteration if self.fit_clock_s is not None else 0
        rate = done / run_s if run_s > 0 and done > 0 else None
        status = {
            "state": state,
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "run_dir": str(self.run_dir),
            "iteration": iteration,
            "total": total,
            "it_per_s": rate,
            "eta_s": (total - iteration) / rate if rate else None,
            "elapsed_s": round(now - self.clock0_s, 1),
            "max_minutes": max_minutes,
            "updated": time.time(),
            "loss": loss,
            "val": val,
            "checkpoint_iteration": checkpoint_iteration,
            **extra,
        }
        self.run_dir.mkdir(parents=True, exist_ok=True)
        write_json(self.run_dir / STATUS, status)
        self.written_s = now

    def log(self, record: dict) -> None:
        """Append ``record`` as one line of ``log.jsonl``."""
        if self.enabled:
            with open(self.run_dir / LOG, "a") as f:
                f.write(json.dumps(record) + "\n")

    def truncate_log(self, iteration: int) -> None:
        """Drop the ``log.jsonl`` lines of iterations after ``iteration`` (those a killed run logged after its last
        checkpoint: the resumed run trains them again), atomically."""
        if not self.enabled:
            return
        path = self.run_dir / LOG
        try:
            lines = path.read_text().splitlines(keepends=True)
        except FileNotFoundError:
            return
        except (OSError, UnicodeDecodeError) as exc:
            raise D2TurbError(f"{path}: cannot read ({exc.__class__.__name__}: {exc})") from exc

        def kept(line: str) -> bool:
            try:
                record = json.loads(line)
            except ValueError:
                return False  # a line cut by the kill
            return not (isinstance(record, dict) and isinstance(record.get("iter"), int) and record["iter"] > iteration)

        keep = [line for line in lines if kept(line)]
        if keep != lines:
            write_text(path, "".join(line if line.endswith("\n") else line + "\n" for line in keep))
