"""One set of CLI defaults (d2turb.defaults): every command with --depth, --device, --png-compression or
--max-pixels takes the value defined there and shows it in its --help."""

import re

import pytest

from d2turb.cli import main
from d2turb.defaults import DEFAULT_DEPTH, DEFAULT_DEVICE, DEFAULT_MAX_PIXELS, DEFAULT_PNG_LEVEL

# option → (its default, commands that have it); the commands are listed by hand, so that one losing an option
# (or a new command with one missing here) fails below
OPTIONS = {
    "--depth": (DEFAULT_DEPTH, ["simulate", "simulate-video", "make-dataset"]),
    "--device": (
        DEFAULT_DEVICE,
        ["simulate", "simulate-video", "make-dataset", "restore", "evaluate", "demo", "bench model"],
    ),
    "--png-compression": (DEFAULT_PNG_LEVEL, ["simulate", "make-dataset", "restore"]),
    "--max-pixels": (DEFAULT_MAX_PIXELS, ["simulate", "simulate-video", "make-dataset", "restore", "evaluate"]),
}
COMMANDS = sorted({c for _, commands in OPTIONS.values() for c in commands} | {"train", "check-dataset", "convert"})


def _help(capsys, command: str) -> str:
    assert main([*command.split(), "--help"]) == 0
    return re.sub(r"\s+", " ", capsys.readouterr().out)  # argparse wraps the text at the terminal width


def _option_help(text: str, option: str) -> str | None:
    """The help text of ``option`` (from its line in the options list to the next option)."""
    match = re.search(rf" {re.escape(option)}(?: [A-Z]+)? (?!\[)(.*?)(?= --[a-z]|$)", text.split("options:", 1)[-1])
    return match.group(1) if match else None


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_shows_the_shared_defaults(command, capsys):
    text = _help(capsys, command)
    for option, (default, commands) in OPTIONS.items():
        entry = _option_help(text, option)
        if command in commands:
            assert entry is not None, (command, option)
            assert f"default {default}" in entry, (command, option, entry)
        else:
            assert entry is None, (command, option, "has the option: add it to OPTIONS")


def test_the_parsed_defaults_are_the_shared_ones():
    """Not only the text: the value argparse hands to each command is d2turb.defaults'."""
    from d2turb.cli import build_parser

    parser = build_parser()
    dests = {"--depth": "depth", "--device": "device", "--png-compression": "png_level", "--max-pixels": "max_pixels"}
    required = {
        "simulate": ["x.png", "--out", "o"],
        "simulate-video": ["x.png", "--out", "o"],
        "make-dataset": ["--clean", "c", "--out", "o", "--pairs", "1"],
        "restore": ["x.png", "--weights", "input", "--out", "o"],
        "evaluate": ["--real", "r", "--out", "o"],
        "demo": ["--out", "o"],
        "bench model": ["nafnet"],
    }
    for option, (default, commands) in OPTIONS.items():
        for command in commands:
            args = parser.parse_args([*command.split(), *required[command]])
            assert getattr(args, dests[option]) == default, (command, option)
