"""One definition of the optics (issue 39): the defaults live in d2turb.defaults only, one Optics class, and every
command that takes optics spells them the same way (--aperture, --wavelength, --ifov, --path-length), with the old
``--param aperture_m=…`` of restore, measure and make-dataset kept as an alias for one release."""

import ast
import io
import tokenize
from pathlib import Path

import pytest

from d2turb.cli import build_parser, main
from d2turb.commands.common import OPTICS_FLAGS
from d2turb.defaults import DEFAULT_APERTURE_M, DEFAULT_PATH_LENGTH_M, DEFAULT_WAVELENGTH_M
from d2turb.errors import D2TurbError
from d2turb.sim.optics import Optics

# listed by hand: a command losing the flags, or a new one with some of them only, fails below
OPTICS_COMMANDS = ["demo", "make-dataset", "measure", "restore", "simulate", "simulate-video"]


def _signature(action):
    return action.option_strings, action.nargs, action.type, action.metavar


def test_every_optics_command_accepts_the_same_flags():
    parser = build_parser()
    flags = set(OPTICS_FLAGS.values())
    taking, spelling = [], {}
    for name, command in parser.commands.items():
        actions = {a.option_strings[0]: a for a in command._actions if a.option_strings}
        if flags & set(actions):
            assert flags <= set(actions), (name, sorted(flags - set(actions)))
            taking.append(name)
            for flag in flags:  # the same option: name, number of values, type, metavar
                spelling.setdefault(flag, _signature(actions[flag]))
                assert _signature(actions[flag]) == spelling[flag], (name, flag)
    assert sorted(taking) == OPTICS_COMMANDS


def test_the_default_optics_are_defined_once():
    from d2turb.app.core import SimSettings, parse_wavelengths_nm
    from d2turb.clip import Optics as ClipOptics
    from d2turb.sim import Optics, TurbulenceParams, make_params

    assert ClipOptics is Optics
    o, p, m = Optics(), TurbulenceParams(), make_params()
    for x in (o, p, m, p.optics):
        assert (x.aperture_m, x.wavelength_m) == (DEFAULT_APERTURE_M, DEFAULT_WAVELENGTH_M)
    assert p.path_length_m == m.path_length_m == DEFAULT_PATH_LENGTH_M and o.path_length_m is None
    assert o.ifov_rad == p.ifov_rad and not o.ifov_known and p.optics.ifov_known
    assert o.lambda_over_d_px == p.lambda_over_d_px == 2.0
    s = SimSettings()
    assert (s.aperture_m, s.path_length_m) == (DEFAULT_APERTURE_M, DEFAULT_PATH_LENGTH_M)
    assert parse_wavelengths_nm(s.wavelength_nm) == [DEFAULT_WAVELENGTH_M]
    args = build_parser().parse_args(["simulate", "x.png", "--out", "o"])
    assert (args.aperture, args.wavelength, args.path_length) == (DEFAULT_APERTURE_M, [525e-9], 1000.0)


def test_no_optics_default_is_written_outside_defaults_py():
    """No number literal of the default wavelength in src/ but d2turb/defaults.py, nor of the default aperture on a
    line about the aperture (docstrings and comments may name them)."""
    src = Path(__file__).resolve().parents[1] / "src" / "d2turb"
    found = []
    for path in src.rglob("*.py"):
        if path.name == "defaults.py" and path.parent == src:
            continue
        text = path.read_text(encoding="utf-8")
        lines = text.splitlines()
        for tok in tokenize.generate_tokens(io.StringIO(text).readline):
            if tok.type != tokenize.NUMBER or not isinstance(value := ast.literal_eval(tok.string), float):
                continue
            line = lines[tok.start[0] - 1]
            if value == DEFAULT_WAVELENGTH_M or (value == DEFAULT_APERTURE_M and "aperture" in line.lower()):
                found.append(f"{path.relative_to(src)}:{tok.start[0]}: {line.strip()}")
    assert not found, found


def test_the_old_param_spelling_is_an_alias_with_a_warning(capsys):
    from d2turb.commands import make_dataset, measure, restore

    parser = build_parser()
    new = parser.parse_args(["measure", "c", "--out", "o", "--aperture", "0.2", "--ifov", "2e-6", "--fps", "25"])
    old = parser.parse_args(
        ["measure", "c", "--out", "o", "--param", "aperture_m=0.2", "--param", "ifov_rad=2e-6", "--param", "fps=25"]
    )
    assert measure.optics_of(new) == measure.optics_of(old) == {"aperture_m": 0.2, "ifov_rad": 2e-6, "fps": 25}
    assert measure.optics_of(parser.parse_args(["measure", "c", "--out", "o"])) == {}
    rgb = parser.parse_args(["measure", "c", "--out", "o", "--wavelength", "6.3e-7", "5.25e-7", "4.5e-7"])
    assert measure.optics_of(rgb) == {"wavelength_m": [6.3e-7, 5.25e-7, 4.5e-7]}
    assert Optics(**measure.optics_of(rgb)).wavelength_m == 5.25e-7  # the reference (middle) wavelength
    clash = parser.parse_args(["measure", "c", "--out", "o", "--aperture", "0.2", "--param", "aperture_m=0.3"])
    with pytest.raises(D2TurbError, match="aperture_m given twice"):
        measure.optics_of(clash)
    r_new = parser.parse_args(["restore", "c", "--temporal", "8", "--out", "o", "--wavelength", "6e-7"])
    r_old = parser.parse_args(["restore", "c", "--temporal", "8", "--out", "o", "--param", "wavelength_m=6e-7"])
    assert restore._optics(r_new) == restore._optics(r_old) == Optics(wavelength_m=6e-7)
    d_old = parser.parse_args(
        ["make-dataset", "--clean", "c", "--out", "o", "--pairs", "1", "--param", "ifov_rad=3e-6"]
    )
    params = make_dataset.parse_params(d_old.param)
    params.update(make_dataset.optics_given(d_old, params))
    assert params == {"ifov_rad": 3e-6}
    # the alias says so, on the command line, in one warning line naming the flag
    capsys.readouterr()
    assert main(["measure", "nothing", "--out", "o", "--param", "path_length_m=500"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0].startswith("warning: --param path_length_m=… is the old spelling of --path-length"), err
    assert err[1].startswith("error:") and len(err) == 2, err
