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


def test_the_tile_dr0_and_window_defaults_are_read_from_defaults_py():
    """Tile, overlap, D/r0 and the two clip windows are defined once in d2turb.defaults: the command line, the
    library, the evaluation and the page take them from there (their values are checked, not only the names)."""
    import inspect

    from d2turb.app import forms, tabs
    from d2turb.cli import build_parser
    from d2turb.clip import ClipRestorer
    from d2turb.defaults import DEFAULT_DR0, DEFAULT_OVERLAP_PX, DEFAULT_TEMPORAL, DEFAULT_TILE_PX, MEASURED_TEMPORAL
    from d2turb.eval.clips import evaluate_clips
    from d2turb.eval.synthetic import evaluate_synthetic
    from d2turb.restore import Restorer
    from d2turb.restore.clip_build import clip_deblur
    from d2turb.restore.files import RestoreOptions
    from d2turb.sim import TurbulenceParams

    def default(fn, name):
        return inspect.signature(fn).parameters[name].default

    args = build_parser().parse_args(["restore", "x.png", "--weights", "input", "--out", "o"])
    for fn in (Restorer, tabs.run_restore, evaluate_synthetic, clip_deblur):
        assert (default(fn, "tile"), default(fn, "overlap")) == (DEFAULT_TILE_PX, DEFAULT_OVERLAP_PX), fn
    assert (args.tile, args.overlap) == (RestoreOptions().tile, RestoreOptions().overlap)
    assert (args.tile, args.overlap) == (DEFAULT_TILE_PX, DEFAULT_OVERLAP_PX)
    assert TurbulenceParams().dr0 == forms.SimSettings().dr0 == DEFAULT_DR0
    assert default(ClipRestorer, "temporal") == DEFAULT_TEMPORAL
    assert default(evaluate_clips, "temporal") == default(tabs.run_clip, "temporal") == MEASURED_TEMPORAL


def test_no_tile_or_overlap_default_is_written_outside_defaults_py():
    """No number literal of the default tile on a line about tiles, nor of the default overlap on a line about the
    overlap, in src/ but d2turb/defaults.py (docstrings and comments may name them)."""
    import ast
    import io
    import tokenize
    from pathlib import Path

    from d2turb.defaults import DEFAULT_OVERLAP_PX, DEFAULT_TILE_PX

    src = Path(__file__).resolve().parents[1] / "src" / "d2turb"
    found = []
    for path in src.rglob("*.py"):
        if path == src / "defaults.py":
            continue
        text = path.read_text(encoding="utf-8")
        lines = text.splitlines()
        for tok in tokenize.generate_tokens(io.StringIO(text).readline):
            if tok.type != tokenize.NUMBER:
                continue
            value, line = ast.literal_eval(tok.string), lines[tok.start[0] - 1].split("#")[0].lower()  # its code
            if (value == DEFAULT_TILE_PX and "tile" in line) or (value == DEFAULT_OVERLAP_PX and "overlap" in line):
                found.append(f"{path.relative_to(src)}:{tok.start[0]}: {line.strip()}")
    assert not found, found
