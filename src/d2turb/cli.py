"""The ``d2turb`` command line. Each subcommand lives in ``d2turb/commands/<name>.py`` and exposes
``register(subparsers)``; heavy imports happen inside the command, so ``d2turb --help`` is fast."""

from __future__ import annotations

import argparse
import contextlib
import importlib
import re
import signal
import sys
import threading

from d2turb import __version__
from d2turb.commands.common import apply_wait_policy, log_to_stderr
from d2turb.defaults import DEFAULT_MAX_PIXELS
from d2turb.errors import D2TurbError

COMMANDS = [
    "demo",
    "simulate",
    "simulate_video",
    "make_dataset",
    "check_dataset",
    "models",
    "bench",
    "convert",
    "restore",
    "measure",
    "evaluate",
    "train",
    "pack",
    "app",
]


class Parser(argparse.ArgumentParser):
    """argparse with two fixes: a negative number in scientific notation after a space (``--cn2 -1e-14``)
    is a value, not an option; usage errors are one ``error:`` line, like every other error."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")

    def error(self, message: str):
        self.exit(2, f"error: {message} (see: {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="d2turb", description="Depth-aware atmospheric turbulence: simulate, restore, evaluate.")
    parser.add_argument("--version", action="version", version=f"d2turb {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"d2turb.commands.{name}").register(sub)
    parser.commands = sub.choices  # name -> the command's parser
    return parser


# parameters named with their unit, whose flag has the short name: the message keeps the name, the flag beside it
UNIT_PARAMS = {
    "wavelength_m": "wavelength",
    "ifov_rad": "ifov",
    "aperture_m": "aperture",
    "path_length_m": "path_length",
}


def flag_words(exc: D2TurbError, command: argparse.ArgumentParser | None) -> str:
    """The message of a library error with the parameter it starts with (``exc.param``) named by the command's flag
    for it: ``patch must be…`` → ``--patch must be…``, ``ifov_rad = …`` → ``ifov_rad (--ifov) = …``; as it is when
    the command has no such flag."""
    message, param = str(exc), getattr(exc, "param", None)
    if command is None or param is None or not message.startswith(param):
        return message
    flags = {action.dest: max(action.option_strings, key=len) for action in command._actions if action.option_strings}
    if param in flags:
        return flags[param] + message[len(param) :]
    if UNIT_PARAMS.get(param) in flags:
        return f"{param} ({flags[UNIT_PARAMS[param]]})" + message[len(param) :]
    return message


def _end_progress_bars() -> None:
    """Close live tqdm bars, so the next line starts on a line of its own, not inside a bar's line."""
    tqdm_module = sys.modules.get("tqdm")
    if tqdm_module is None:
        return
    for bar in list(getattr(tqdm_module.tqdm, "_instances", ())):
        with contextlib.suppress(Exception):
            bar.close()


def _listen_to_ctrl_c():
    """Ctrl-C (SIGINT) stops every command: the command's cleanup runs (temp files removed, finished outputs kept)
    and it exits 130. A process started with SIGINT ignored (``cmd &`` in a script, some job runners) would
    otherwise inherit that and run to the end; like ffmpeg, d2turb takes SIGINT back. Returns the undo."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) != signal.SIG_IGN:
        return lambda: None
    signal.signal(signal.SIGINT, signal.default_int_handler)
    return lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, or a usage error already printed in one line
        return exc.code if isinstance(exc.code, int) else 0
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    log_to_stderr()
    restore_sigint = _listen_to_ctrl_c()
    apply_wait_policy(args)  # before torch is imported
    from d2turb.io import set_max_pixels  # lazy: d2turb.io imports torch, which --help and usage errors never need

    set_max_pixels(getattr(args, "max_pixels", DEFAULT_MAX_PIXELS))
    try:
        return int(args.func(args) or 0)
    except D2TurbError as exc:
        _end_progress_bars()
        message = flag_words(exc, parser.commands.get(args.command))
        print("error: " + " ".join(message.split()), file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        _end_progress_bars()
        print("interrupted", file=sys.stderr)
        return 130
    finally:
        set_max_pixels(DEFAULT_MAX_PIXELS)
        restore_sigint()


if __name__ == "__main__":
    sys.exit(main())
