"""Options and behaviour shared by the subcommands: seed range, device, image-size limit, PNG level, the
rule for folders with bad files (``FileErrors``, from :mod:`d2turb.errors`, in the file-job skeleton of simulate and
restore, :class:`d2turb.io.jobs.FileJob`: every readable file is processed, one ``error:`` line per bad file, a
summary, exit status 1; ``--fail-fast`` stops at the first), and the stderr handler of the ``d2turb`` loggers."""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys

from d2turb.defaults import (
    DEFAULT_APERTURE_M,
    DEFAULT_DEPTH,
    DEFAULT_DEVICE,
    DEFAULT_MAX_PIXELS,
    DEFAULT_PATH_LENGTH_M,
    DEFAULT_PNG_LEVEL,
    DEFAULT_WAVELENGTH_M,
    DEVICE_HELP,
)
from d2turb.errors import D2TurbError

log = logging.getLogger("d2turb.commands")

SEED_MAX = 2**63 - 1  # torch generators and numpy SeedSequence both take [0, 2**63 - 1]


def seed_type(text: str) -> int:
    try:
        value = int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if not 0 <= value <= SEED_MAX:
        raise argparse.ArgumentTypeError(f"must be between 0 and 2**63 - 1, got {text}")
    return value


def _bounded_int(lo: int, hi: int | None = None):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if value < lo or (hi is not None and value > hi):
            raise argparse.ArgumentTypeError(
                f"must be {lo} or more, got {value}" if hi is None else f"must be between {lo} and {hi}, got {value}"
            )
        return value

    return parse


def add_seed_arg(p, help_text: str = "random seed (default 0)") -> None:
    p.add_argument("--seed", type=seed_type, default=0, metavar="N", help=help_text)


def add_device_arg(p) -> None:
    p.add_argument(
        "--device", default=DEFAULT_DEVICE, metavar="DEVICE", help=f"{DEVICE_HELP} (default {DEFAULT_DEVICE})"
    )


def add_depth_arg(p, forms: str, what: str = "") -> None:
    """``--depth SPEC`` with the default of d2turb.defaults; ``forms``: the SPECs the command takes."""
    p.add_argument(
        "--depth",
        default=DEFAULT_DEPTH,
        metavar="SPEC",
        help=f"relative depth (far = 1): {forms}{what} (default {DEFAULT_DEPTH}: the weight-free prior, far = top)",
    )


def add_motion_args(p) -> None:
    """The options of a turbulent clip (frozen-flow layers moved by the wind), shared by ``simulate-video`` and
    ``make-dataset --frames``."""
    p.add_argument("--fps", type=float, default=30.0, help="frames per second (default 30)")
    p.add_argument(
        "--wind",
        type=float,
        nargs="+",
        default=[1.0],
        metavar="V",
        help="transverse wind in m/s (default 1); several values: speeds from the aperture to the object, "
        "interpolated along the path",
    )
    p.add_argument(
        "--wind-dir", type=float, default=0.0, metavar="DEG", help="drift direction in the image (0 = +x, 90 = +y)"
    )
    p.add_argument(
        "--boil", type=float, default=0.0, metavar="X", help="fraction of each layer's variance refreshed per frame"
    )


def wait_passively(p, when=None) -> None:
    """Mark a command whose CPU work should run with ``OMP_WAIT_POLICY=PASSIVE`` (see :func:`apply_wait_policy`);
    ``when(args)``: only for the parsed arguments it accepts."""
    p.set_defaults(passive_openmp=when or True)


def apply_wait_policy(args) -> None:
    """``OMP_WAIT_POLICY=PASSIVE`` for a command marked by :func:`wait_passively`, unless the user set a policy.

    Called by ``d2turb.cli.main`` before torch is imported (OpenMP reads the variable once, when torch loads it).
    By default OpenMP threads spin between parallel regions; on a CPU that other processes also use, torch's two
    threads then spin against them and every region waits for a descheduled thread: on a shared 2-core machine
    (load 14–17) simulate-video took 268 s for 64 frames of 512x384 instead of 21 s, make-dataset 26 s to its
    first pair instead of 4 (medians; benchmarks/RESULTS.md, "Time to first output"). Waiting threads sleep; the
    outputs are the same (the work is split among the threads as before). Once torch is loaded (``main`` called
    in a process that imported it) the setting could no longer act, and the environment is left as it is."""
    passive = getattr(args, "passive_openmp", False)
    if (passive(args) if callable(passive) else passive) and "torch" not in sys.modules:
        os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def add_param_arg(p, help_text: str = "simulator parameter override (repeatable)") -> None:
    """``--param KEY=VALUE`` (repeatable): a ``TurbulenceParams`` field, the value parsed as JSON (else text)."""
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE", help=help_text)


def parse_params(texts: list[str], keys=None) -> dict:
    """``--param`` values → {key: value}, each value parsed as JSON (else kept as text); a malformed item, or a key
    not in ``keys`` (when given), is a one-line error."""
    params = {}
    for text in texts:
        key, sep, value = text.partition("=")
        if not sep or not key:
            raise D2TurbError(f"--param expects KEY=VALUE, got {text!r}")
        if keys is not None and key not in keys:
            raise D2TurbError(f"--param {key}: unknown key; choose from {', '.join(keys)}")
        try:
            params[key] = json.loads(value)
        except json.JSONDecodeError:
            params[key] = value
    return params


def model_config(text: str | None) -> dict:
    """A ``--config`` value → the model config (a dict; ``{}`` when not given): ``text`` is the JSON object itself or
    the path of a .json file holding it. Not JSON, or not an object: a one-line ``D2TurbError``."""
    from pathlib import Path

    if not text:
        return {}
    if text.endswith(".json") and Path(text).is_file():
        text = Path(text).read_text()
    try:
        cfg = json.loads(text)
    except ValueError as exc:
        raise D2TurbError(f"--config: not valid JSON ({exc})") from exc
    if not isinstance(cfg, dict):
        raise D2TurbError("--config: expected a JSON object")
    return cfg


# ---- the optics (d2turb.sim.Optics): one spelling on every command that takes them --------------------------------
# field → flag (argparse dest: the flag's name with _); `--param FIELD=…` is the old spelling of restore, measure and
# make-dataset, kept as an alias for one release (a warning line names the flag)
OPTICS_FLAGS = {
    "aperture_m": "--aperture",
    "wavelength_m": "--wavelength",
    "ifov_rad": "--ifov",
    "path_length_m": "--path-length",
}


def add_optics_args(
    p,
    path_length_m: float | None = DEFAULT_PATH_LENGTH_M,
    *,
    given_only: bool = False,
    ifov_help: str = "default Nyquist λ/(2D)",
    path_help: str | None = None,
    wavelength_note: str = "",
) -> None:
    """``--aperture M``, ``--wavelength M [M M]``, ``--ifov RAD``, ``--path-length M``: the optics, with the defaults
    of d2turb.defaults. ``given_only``: every value None unless given (the command fills in what is not given, and
    records what was: :func:`optics_given`); ``path_length_m`` None: no default path length (``path_help`` says
    what then); ``wavelength_note``: appended to the wavelength's "R G B"."""
    default = (lambda v: None) if given_only else (lambda v: v)
    p.add_argument(
        "--aperture",
        type=float,
        default=default(DEFAULT_APERTURE_M),
        metavar="M",
        help=f"aperture diameter D in metres (default {DEFAULT_APERTURE_M:g})",
    )
    p.add_argument(
        "--wavelength",
        type=float,
        nargs="+",
        default=default([DEFAULT_WAVELENGTH_M]),
        metavar="M",
        help=f"wavelength in metres, one value or three (R G B{wavelength_note}) "
        f"(default {DEFAULT_WAVELENGTH_M * 1e9:g}e-9)",
    )
    p.add_argument(
        "--path-length",
        type=float,
        default=default(path_length_m),
        metavar="M",
        help=f"path length L in metres ({path_help or f'default {path_length_m:g}'})",
    )
    p.add_argument("--ifov", type=float, default=None, metavar="RAD", help=f"pixel angular size ({ifov_help})")


def optics_given(args, params: dict | None = None) -> dict:
    """The optics given on the command line as {Optics field: value}: the flags of :func:`add_optics_args` and, the
    old spelling, the optics keys of ``params`` (parsed ``--param``; removed from it, one warning line each). The
    same field given both ways with different values is a one-line error. Three wavelengths: a list (as in JSON)."""
    given = {}
    for key, flag in OPTICS_FLAGS.items():
        value = getattr(args, flag[2:].replace("-", "_"), None)
        if key == "wavelength_m" and value is not None:
            value = list(value) if len(value) > 1 else value[0]
        if params is not None and key in params:
            old = params.pop(key)
            log.warning("--param %s=… is the old spelling of %s (kept until the next release)", key, flag)
            if value is not None and old != value:
                raise D2TurbError(f"{key} given twice: {flag} {value} and --param {key}={old}")
            value = old
        if value is not None:
            given[key] = value
    return given


def add_max_pixels_arg(p) -> None:
    """Images whose header claims more pixels are refused before decoding (applied by ``d2turb.cli.main``)."""
    p.add_argument(
        "--max-pixels",
        type=_bounded_int(0),
        default=DEFAULT_MAX_PIXELS,
        metavar="N",
        help=f"refuse input images larger than N pixels, a guard against decompression bombs "
        f"(default {DEFAULT_MAX_PIXELS}, Pillow's limit; 0 = no limit)",
    )


def add_png_level_arg(p) -> None:
    p.add_argument(
        "--png-compression",
        dest="png_level",
        type=_bounded_int(0, 9),
        default=DEFAULT_PNG_LEVEL,
        metavar="LEVEL",
        help=f"zlib level of the PNG outputs, 0-9 (default {DEFAULT_PNG_LEVEL}: fast; 9: smallest files)",
    )


def add_fail_fast_arg(p) -> None:
    p.add_argument(
        "--fail-fast",
        action="store_true",
        help="stop at the first unreadable or failing input (default: report it, go on, exit 1 at the end)",
    )


class StderrHandler(logging.Handler):
    """One line per record on the current ``sys.stderr`` (looked up each time, so captured streams work), above
    any live progress bar; warnings and errors start with ``warning:`` / ``error:``."""

    def emit(self, record: logging.LogRecord) -> None:
        text = self.format(record)
        if record.levelno >= logging.WARNING:
            text = f"{record.levelname.lower()}: {text}"
        if "tqdm" in sys.modules:
            from tqdm import tqdm

            tqdm.write(text, file=sys.stderr)
        else:
            print(text, file=sys.stderr)


def log_to_stderr(level_of: dict[str, int] | None = None) -> None:
    """Send the ``d2turb`` loggers' records to stderr (once per process); ``level_of`` lowers the level of
    named child loggers (e.g. ``{"d2turb.train": logging.INFO}`` for training progress)."""
    root = logging.getLogger("d2turb")
    if not any(isinstance(h, StderrHandler) for h in root.handlers):
        root.addHandler(StderrHandler())
    for name, level in (level_of or {}).items():
        logging.getLogger(name).setLevel(level)
