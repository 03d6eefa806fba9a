"""The commands the page runs: each job is ONE argument list (``simulate_argv``, ``restore_argv``,
``clip_simulate_argv``, ``clip_argv``), and that very list is both what runs and what the page shows.

Why a child process. The page (``d2turb.app``) sits one floor below the command line (``d2turb.commands`` and
``d2turb.cli`` import the library and ``d2turb.app``; the page never imports them, so the arrows between the two
point one way and there is no cycle; ``farm-studio look`` checks it). The page therefore cannot call the command's
parser in-process; instead :func:`run_command` runs ``python -m d2turb ARGV`` in the run folder: the command's own
parser and ``run``, exactly as a user's shell would, with no second, hand-written copy of the library call to keep
in sync. The page shows ``shlex.join(["d2turb", *argv])`` of the same list (:func:`command_text`) and writes it to
``command.sh``, so the command pasted into a shell in the unpacked download writes the same files bit for bit
(tests/test_app.py runs it for every job kind).

What the page checks before a job (sizes, file types, physics, depth maps) are library calls that raise one-line
:class:`~d2turb.errors.D2TurbError` messages with the user's own names; an error the command itself prints
(``error: ...``) becomes the same one-line message in the page.
"""

from __future__ import annotations

import os
import re
import shlex
import site
import subprocess
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import d2turb
from d2turb import __version__
from d2turb.app.forms import SimValues, fmt_float
from d2turb.errors import D2TurbError
from d2turb.io import write_text

CLIP_SIM_FRAMES = 32  # frames simulated from an image uploaded to the Clip tab

Progress = Callable[[float, str], None]  # (fraction done, what is running)


# ---- the argument lists (without the leading ``d2turb``) ----------------------------------------------------------
def simulate_argv(v: SimValues, input_name: str, out: str = "out") -> list[str]:
    """``d2turb simulate`` for the checked values of the Simulate tab."""
    argv = ["simulate", input_name, "--out", out, "--seed", str(v.seed)]
    argv += ["--dr0", fmt_float(v.dr0)] if v.dr0 is not None else ["--cn2", fmt_float(v.cn2)]
    argv += ["--depth", v.depth] + (["--disparity"] if v.disparity else [])
    o = v.optics
    argv += ["--aperture", fmt_float(o.aperture_m)]
    argv += ["--wavelength", *[fmt_float(w) for w in o.wavelengths]]
    argv += ["--path-length", fmt_float(o.path_length_m)]
    if o.ifov_known:
        argv += ["--ifov", fmt_float(o.ifov_rad)]
    argv += ["--modulation", v.modulation, "--offset", fmt_float(v.offset_s), "--save-flow"]
    return argv


def restore_argv(input_name: str, weights: str, tile: int, overlap: int, device: str, out: str = "out") -> list[str]:
    """``d2turb restore`` of the Restore tab; ``device`` "cpu" is left to the command's default."""
    argv = ["restore", input_name, "--weights", weights, "--out", out, "--tile", str(tile), "--overlap", str(overlap)]
    return argv + (["--device", device] if device != "cpu" else []) + ["--save-flow"]


def clip_simulate_argv(image_name: str, dr0: float, out: str = "clip") -> list[str]:
    """``d2turb simulate-video``: the Clip tab's clip of ``CLIP_SIM_FRAMES`` frames from an uploaded image (wind
    2 m/s, boiling 0.1, no mp4); its frames are ``OUT/turb``."""
    argv = ["simulate-video", image_name, "--out", out, "--frames", str(CLIP_SIM_FRAMES), "--dr0", f"{dr0:g}"]
    return argv + ["--wind", "2", "--boil", "0.1", "--no-mp4"]


def clip_argv(clip: str, temporal: int, dr0: float | None, out: str = "out") -> list[str]:
    """``d2turb restore --temporal`` of the Clip tab; no ``dr0``: fusion without deblurring."""
    argv = ["restore", clip, "--temporal", str(temporal), "--out", out, "--save-intermediate"]
    return argv + (["--dr0", f"{dr0:g}"] if dr0 else ["--deblur", "none"])


# ---- showing and running them ------------------------------------------------------------------------------------
def command_text(*argvs: Sequence[str]) -> str:
    """The command lines as the page shows them: ``d2turb ...``, one line per argument list, run in order."""
    return "\n".join(shlex.join(["d2turb", *argv]) for argv in argvs)


def write_command(path: Path, *argvs: Sequence[str]) -> str:
    """:func:`command_text` of ``argvs``, also written as the executable script ``path``; returns the text."""
    cmd = command_text(*argvs)
    write_text(path, f"#!/bin/sh\n# written by d2turb {__version__} app; run it in this folder\n{cmd}\n")
    path.chmod(0o755)
    return cmd


_PACKAGE_PARENT = str(Path(d2turb.__file__).resolve().parents[1])  # the d2turb this page runs, for the child
_BAR = re.compile(r"^(?:(?P<desc>[^:|]{1,60}): )?\s*(?P<pct>\d{1,3})%\|")  # a tqdm bar's line


def _child_env() -> dict[str, str]:
    env = dict(os.environ)
    folders = [*getattr(site, "getsitepackages", list)(), site.getusersitepackages()]  # (old virtualenv: no list)
    installed = {str(Path(p).resolve()) for p in folders}
    if _PACKAGE_PARENT not in installed:  # a checkout on PYTHONPATH or an editable install: the same source tree
        env["PYTHONPATH"] = os.pathsep.join(p for p in (_PACKAGE_PARENT, env.get("PYTHONPATH")) if p)
    env["PYTHONSAFEPATH"] = "1"  # Python >= 3.11: the run folder (the child's cwd) is not put on sys.path
    return env


def run_command(argv: Sequence[str], cwd: Path, progress: Progress | None = None) -> None:
    """Run ``d2turb *argv`` in ``cwd`` as the command line does (a child ``python -m d2turb``). Its tqdm bars
    (stderr) are passed to ``progress``, its other lines to this process's stdout and stderr (the server's log); a
    nonzero exit status raises a one-line D2TurbError: the command's first ``error:`` line, else its last line on
    stderr, else the status."""
    argv = [str(a) for a in argv]
    errors: list[str] = []
    last = ""

    def line(raw: bytes) -> None:
        nonlocal last
        text = raw.decode("utf-8", "replace").strip()
        if not text:
            return
        bar = _BAR.match(text)
        if bar:
            if progress is not None:
                progress(min(int(bar["pct"]), 100) / 100, (bar["desc"] or argv[0]).strip())
        else:
            print(text, file=sys.stderr, flush=True)  # the server's log, as when the job ran in its process
            if text.startswith("error:"):
                errors.append(text[len("error:") :].strip())
            else:
                last = text

    proc = subprocess.Popen(
        [sys.executable, "-m", "d2turb", *argv],
        cwd=cwd,
        env=_child_env(),
        stdin=subprocess.DEVNULL,
        stdout=None,  # the command's report lines go to the server's log
        stderr=subprocess.PIPE,
    )
    try:
        pending = b""
        for chunk in iter(lambda: proc.stderr.read1(1 << 16), b""):
            *done, pending = re.split(rb"[\r\n]", pending + chunk)
            for raw in done:
                line(raw)
        line(pending)
        status = proc.wait()
    except BaseException:  # the page stops (Ctrl+C): the job goes with it
        proc.kill()
        proc.wait()
        raise
    finally:
        proc.stderr.close()
    if status:
        failed = f"d2turb {argv[0]} failed (exit status {status})"
        raise D2TurbError(errors[0] if errors else f"{failed}: {last}" if last else failed)
