"""The ``d2turb`` command line. Each subcommand lives in ``d2turb/commands/<name>.py`` and exposes
``register(subparsers)``; heavy imports happen inside the command, so ``d2turb --help`` is fast."""

from __future__ import annotations

import argparse
import importlib
import sys

from d2turb import __version__
from d2turb.errors import D2TurbError

COMMANDS = [
    "demo",
    "simulate",
    "make_dataset",
    "check_dataset",
    "models",
    "bench",
    "restore",
    "evaluate",
    "train",
    "pack",
    "app",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="d2turb", description="Depth-aware atmospheric turbulence: simulate, restore, evaluate."
    )
    parser.add_argument("--version", action="version", version=f"d2turb {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"d2turb.commands.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except D2TurbError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
