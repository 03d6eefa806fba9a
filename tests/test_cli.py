"""The command line's contract across commands (d2turb.cli, d2turb.commands.common): every bad input is one
`error:` line with a stated exit status, bad --out, --device and --seed are refused before any work, outputs are
readable by others, unreadable things and odd file names are named in one line."""

import json
import math
import os
import stat
from pathlib import Path

import numpy as np
import pytest
import torch
from hostile_input import (
    TINY_NAFNET,
    dead_pid,
    error_lines,
    make_dataset_args,
    one_error_line,
    png_bomb,
    rgb,
    run_cli,
    temp_files,
    tiny_config,
    tiny_pairs,
)
from PIL import Image

from d2turb.cli import main
from d2turb.defaults import DEFAULT_MAX_PIXELS
from d2turb.io import write_image


@pytest.mark.parametrize("command", ["simulate", "restore", "evaluate"])
def test_bomb_is_one_line_naming_file_and_size(command, tmp_path, capsys):
    bomb = png_bomb(tmp_path / "bomb.png")
    out = tmp_path / "out"
    argv = {
        "simulate": ["simulate", str(bomb), "--out", str(out)],
        "restore": ["restore", str(bomb), "--weights", "input", "--out", str(out)],
        "evaluate": ["evaluate", "--real", str(tmp_path), "--metrics", "piqe", "--out", str(out)],
    }[command]
    rc, _, err = run_cli(capsys, argv)
    assert rc == 2
    one_error_line(err, "bomb.png", "100000x100000", "--max-pixels")
    assert not out.exists() or not any(out.rglob("*"))


def test_max_pixels_is_the_documented_switch(tmp_path, capsys):
    image = rgb(tmp_path / "in" / "a.png", 24, 32)  # 768 pixels
    rc, _, err = run_cli(capsys, ["simulate", str(image), "--out", str(tmp_path / "o"), "--max-pixels", "700"])
    assert rc == 2
    one_error_line(err, "a.png", "32x24", "--max-pixels 768")
    rc, _, _ = run_cli(capsys, ["simulate", str(image), "--out", str(tmp_path / "o"), "--max-pixels", "768"])
    assert rc == 0 and (tmp_path / "o" / "a_turb.png").is_file()
    # lifting the limit lets Pillow try the bomb: it then fails as the broken file it is, in one line. The bomb is
    # just over the default limit (so --max-pixels 0 is what lets it through) and grey (1 byte per pixel): Pillow
    # allocates the claimed image before finding the data missing, ≤ 180 MB here (the 10^10-pixel RGB one above
    # took up to 10 GB of resident memory, depending on the allocator's state)
    side = math.isqrt(DEFAULT_MAX_PIXELS) + 1
    bomb = png_bomb(tmp_path / "bomb.png", side, side, color_type=0)
    rc, _, err = run_cli(
        capsys, ["restore", str(bomb), "--weights", "input", "--out", str(tmp_path / "r"), "--max-pixels", "0"]
    )
    assert rc == 2
    one_error_line(err, "bomb.png", "cannot read")


def _command(name, image, out, dataset_src):
    return {
        "simulate": ["simulate", str(image), "--out", str(out)],
        "simulate-video": ["simulate-video", str(image), "--out", str(out), "--frames", "2", "--no-mp4"],
        "restore": ["restore", str(image), "--weights", "input", "--out", str(out)],
        "make-dataset": make_dataset_args(dataset_src, out),
        "evaluate": ["evaluate", "--real", str(image.parent), "--metrics", "piqe", "--out", str(out)],
        "demo": ["demo", "--out", str(out)],
    }[name]


@pytest.mark.parametrize("command", ["simulate", "simulate-video", "restore", "make-dataset", "evaluate", "demo"])
@pytest.mark.parametrize("kind", ["existing file", "under a file"])
def test_bad_out_is_one_line(command, kind, tmp_path, capsys):
    image = rgb(tmp_path / "in" / "a.png", 64, 64)
    blocker = tmp_path / "blocker"
    blocker.write_text("a file")
    out = blocker if kind == "existing file" else blocker / "sub" / "dir"
    rc, _, err = run_cli(capsys, _command(command, image, out, image.parent))
    assert rc == 2
    one_error_line(err, "--out", str(blocker))
    assert blocker.read_text() == "a file"


@pytest.mark.slow
@pytest.mark.parametrize("command", ["simulate", "restore", "make-dataset", "evaluate"])
def test_read_only_out_is_one_line(command, tmp_path, run_unprivileged):
    """In a process that file permissions bind (as root too: see the run_unprivileged fixture)."""
    image = rgb(tmp_path / "in" / "a.png", 64, 64)
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        proc = run_unprivileged(*_command(command, image, locked / "out", image.parent))
    finally:
        locked.chmod(0o755)
    assert proc.returncode == 2
    one_error_line(proc.stderr, "not writable")
    assert not any(locked.iterdir())


def test_writer_errors_surface_in_the_command(tmp_path, capsys):
    image = rgb(tmp_path / "in" / "a.png")
    out = tmp_path / "out"
    (out / "a_turb.png").mkdir(parents=True)  # a folder where an output file must go
    rc, _, err = run_cli(capsys, ["simulate", str(image), "--out", str(out)])
    assert rc == 2
    one_error_line(err, "cannot write", "a_turb.png")
    assert not temp_files(out)


@pytest.mark.parametrize("command", ["simulate", "simulate-video", "restore", "make-dataset", "evaluate", "demo"])
@pytest.mark.parametrize("device, message", [("bogus", "not a device name"), ("meta", "not supported")])
def test_bad_device_is_one_line(command, device, message, tmp_path, capsys):
    image = rgb(tmp_path / "in" / "a.png", 64, 64)
    rc, _, err = run_cli(capsys, _command(command, image, tmp_path / "out", image.parent) + ["--device", device])
    assert rc == 2
    one_error_line(err, message)
    assert not (tmp_path / "out").exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message on a machine without CUDA")
@pytest.mark.parametrize("command", ["simulate", "simulate-video", "restore", "make-dataset", "evaluate", "demo"])
def test_cuda_without_cuda_is_one_line(command, tmp_path, capsys):
    image = rgb(tmp_path / "in" / "a.png", 64, 64)
    rc, _, err = run_cli(capsys, _command(command, image, tmp_path / "out", image.parent) + ["--device", "cuda"])
    assert rc == 2
    one_error_line(err, "CUDA is not available", "--device cpu")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("command", ["simulate", "simulate-video", "make-dataset", "demo"])
@pytest.mark.parametrize("seed", [str(2**70), "-1", "1.5"])
def test_seed_out_of_range_is_one_line(command, seed, tmp_path, capsys):
    image = rgb(tmp_path / "in" / "a.png", 64, 64)
    rc, _, err = run_cli(capsys, _command(command, image, tmp_path / "out", image.parent) + ["--seed", seed])
    assert rc == 2
    one_error_line(err, "--seed")
    assert not (tmp_path / "out").exists()


def test_largest_seed_works(tmp_path, capsys):
    image = rgb(tmp_path / "in" / "a.png")
    rc, _, _ = run_cli(capsys, ["simulate", str(image), "--out", str(tmp_path / "o"), "--seed", str(2**63 - 1)])
    assert rc == 0
    assert json.loads((tmp_path / "o" / "a_meta.json").read_text())["seed"] == 2**63 - 1


@pytest.fixture
def umask_022():
    old = os.umask(0o022)
    yield
    os.umask(old)


def _modes(root: Path) -> dict[str, int]:
    return {str(p.relative_to(root)): stat.S_IMODE(p.stat().st_mode) for p in root.rglob("*") if p.is_file()}


def test_outputs_are_readable_by_others(umask_022, tmp_path, capsys):
    from d2turb.models import create_model, save_pretrained

    image = rgb(tmp_path / "in" / "a.png")
    assert main(["simulate", str(image), "--out", str(tmp_path / "sim"), "--save-flow"]) == 0
    assert main(make_dataset_args(image.parent, tmp_path / "ds")) == 0
    weights = save_pretrained(create_model("nafnet", **TINY_NAFNET), tmp_path / "w.safetensors")
    assert main(["restore", str(image), "--weights", str(weights), "--out", str(tmp_path / "res")]) == 0
    capsys.readouterr()
    modes = {**_modes(tmp_path / "sim"), **_modes(tmp_path / "ds"), **_modes(tmp_path / "res")}
    modes["w.safetensors"] = stat.S_IMODE(weights.stat().st_mode)
    assert {"a_turb.png", "a_meta.json", "a_fwd_flow_px.npy", "dataset.json", "meta.jsonl", "a_restored.png"} <= {
        Path(k).name for k in modes
    }
    assert any(k.startswith("turb/") for k in modes) and any(k.startswith("bwd_flow_px/") for k in modes)
    assert set(modes.values()) == {0o644}, modes


def test_rerun_removes_temp_files_a_kill_left(tmp_path, capsys):
    image = rgb(tmp_path / "in" / "a.png")
    out = tmp_path / "out"
    out.mkdir()
    leftover = out / f".a_turb.png.{dead_pid()}-deadbeef.tmp.png"
    leftover.write_bytes(b"")
    assert main(["simulate", str(image), "--out", str(out)]) == 0
    assert not temp_files(out) and (out / "a_turb.png").is_file()


@pytest.mark.parametrize("command", ["simulate", "restore", "evaluate"])
def test_inputs_with_the_same_stem_are_refused(command, tmp_path, capsys, astronaut):
    folder = tmp_path / "in"
    write_image(folder / "a.png", astronaut[0, :, :96, :96])
    write_image(folder / "a.jpg", astronaut[0, :, 96:192, :96])
    out = tmp_path / "out"
    argv = {
        "simulate": ["simulate", str(folder / "a.png"), str(folder / "a.jpg"), "--out", str(out)],
        "restore": ["restore", str(folder), "--weights", "input", "--out", str(out)],
        "evaluate": ["evaluate", "--real", str(folder), "--weights", "input", "blur.safetensors", "--out", str(out)],
    }[command]
    if command == "evaluate":
        (tmp_path / "blur.safetensors").write_bytes(b"")
        argv[argv.index("blur.safetensors")] = str(tmp_path / "blur.safetensors")
    rc, _, err = run_cli(capsys, argv)
    assert rc == 2
    one_error_line(err, "same output names", "a.png", "a.jpg")
    assert not out.exists() or not any(out.rglob("*"))


def test_negative_numbers_after_a_space_are_values(tmp_path, capsys):
    image = rgb(tmp_path / "a.png")
    rc, _, err = run_cli(capsys, ["simulate", str(image), "--out", str(tmp_path / "o"), "--cn2", "-1e-14"])
    assert rc == 2
    one_error_line(err, "cn2 must be positive")  # the value reached the parameter check, not argparse
    rc, _, err = run_cli(capsys, ["simulate", str(image), "--out", str(tmp_path / "o"), "--dr0", "-.5"])
    assert rc == 2
    one_error_line(err, "dr0")
    rc, _, err = run_cli(capsys, ["simulate", str(image), "--out", str(tmp_path / "o"), "--no-such-option"])
    assert rc == 2
    one_error_line(err, "--no-such-option", "--help")


@pytest.mark.skipif(os.name != "posix", reason="symbolic links")
@pytest.mark.parametrize("command", ["simulate", "restore"])
def test_dangling_and_looping_links_in_a_folder_are_reported(command, tmp_path, capsys):
    folder = tmp_path / "in"
    rgb(folder / "a.png", 24, 32)
    (folder / "b.png").symlink_to(tmp_path / "nowhere.png")
    (folder / "c.png").symlink_to(folder / "c.png")
    (folder / "d.png").symlink_to(folder / "a.png")  # a working link is an input like any other
    out = tmp_path / "out"
    argv = {"simulate": ["simulate", "--no-tilt"], "restore": ["restore", "--weights", "input"]}[command]
    rc, _, err = run_cli(capsys, [*argv, str(folder), "--out", str(out)])
    assert rc == 1
    lines = error_lines(err)
    assert len(lines) == 2 and "Traceback" not in err
    assert "b.png" in lines[0] and "dangling" in lines[0] and "c.png" in lines[1] and "loop" in lines[1]
    suffix = "turb.png" if command == "simulate" else "restored.png"
    assert {f"a_{suffix}", f"d_{suffix}"} <= {p.name for p in out.iterdir()}


@pytest.mark.slow
@pytest.mark.parametrize(
    "thing", ["input folder", "input file", "clean folder", "config", "dataset.json", "meta.jsonl", "weights"]
)
def test_unreadable_things_are_one_line(thing, tmp_path, run_unprivileged):
    """Mode 000, in a process that file permissions bind (as root too: see the run_unprivileged fixture)."""
    from d2turb.models import create_model, save_pretrained

    folder = tmp_path / "in"
    image = rgb(folder / "a.png", 24, 32)
    root = tiny_pairs(tmp_path / "ds", n=2, size=16, split="test")
    config = tiny_config(tmp_path)
    weights = save_pretrained(create_model("nafnet", **TINY_NAFNET), tmp_path / "w.safetensors")
    evaluate = ["evaluate", "--data", root, "--weights", "input", "--metrics", "psnr", "--out", tmp_path / "o"]
    locked, argv = {
        "input folder": (folder, ["simulate", folder, "--out", tmp_path / "o"]),
        "input file": (image, ["simulate", image, "--out", tmp_path / "o"]),
        "clean folder": (folder, make_dataset_args(folder, tmp_path / "o")),
        "config": (config, ["train", "--config", config, "--out", tmp_path / "o"]),
        "dataset.json": (root / "dataset.json", evaluate),
        "meta.jsonl": (root / "meta.jsonl", evaluate),
        "weights": (weights, ["restore", image, "--weights", weights, "--out", tmp_path / "o"]),
    }[thing]
    mode = locked.stat().st_mode
    locked.chmod(0)
    try:
        proc = run_unprivileged(*argv)
    finally:
        locked.chmod(mode)
    assert proc.returncode == 2, proc.stderr[-2000:]
    line = one_error_line(proc.stderr, str(locked), "Permission denied")
    assert "corrupt" not in line and "FileNotFoundError" not in line


def test_file_name_not_utf8_is_one_error_line_and_nothing_written(tmp_path, capsys):
    """A folder holding a file whose name is not valid UTF-8 (Latin-1 bytes): one `error:` line naming it with
    the bytes escaped, exit 2, no output folder (it used to end in a UnicodeEncodeError traceback; issue 37)."""
    folder = tmp_path / "in"
    folder.mkdir()
    pixels = (np.arange(24 * 32 * 3).reshape(24, 32, 3) % 251).astype(np.uint8)
    Image.fromarray(pixels).save(folder / "ok.png")
    Image.fromarray(pixels).save(os.fsdecode(os.fsencode(folder) + b"/caf\xe9.png"))
    out = tmp_path / "out"
    rc, _, err = run_cli(capsys, ["simulate", str(folder), "--out", str(out)])
    assert rc == 2
    one_error_line(err, "caf\\xe9.png", "not valid UTF-8")
    assert not out.exists()


def test_library_errors_name_the_parameter_the_command_line_its_flag(tmp_path, capsys):
    from d2turb.data.pack import make_pack
    from d2turb.errors import D2TurbError
    from d2turb.sim import TurbulenceParams

    with pytest.raises(D2TurbError, match=r"^quality must be between 1 and 100, got 0$"):
        make_pack([tmp_path], tmp_path / "pack", quality=0)
    with pytest.raises(D2TurbError, match=r"^ifov_rad = 1 rad"):
        TurbulenceParams(ifov_rad=1.0)
    image = rgb(tmp_path / "clean" / "a.png", 64, 64)
    argv = ["make-pack", "--clean", str(image.parent), "--out", str(tmp_path / "pack"), "--quality", "0"]
    rc, _, err = run_cli(capsys, argv)
    assert rc == 2
    one_error_line(err, "--quality must be between 1 and 100, got 0")
    rc, _, err = run_cli(capsys, ["simulate", str(image), "--out", str(tmp_path / "o"), "--ifov", "1"])
    assert rc == 2
    assert one_error_line(err).startswith("error: ifov_rad (--ifov) = 1 rad")


@pytest.mark.parametrize(
    ("argv", "options", "given"),
    [
        (["restore", "a.png", "--out", "o"], "d2turb.restore.files.RestoreOptions", set()),
        (["restore", "a.mp4", "--temporal", "4", "--out", "o"], "d2turb.restore.clip_build.ClipOptions", {"optics"}),
        (["simulate", "a.png", "--out", "o"], "d2turb.data.simulate.SimulateOptions", {"save_tilt"}),
    ],
)
def test_every_job_option_is_an_argument_of_its_command(argv, options, given):
    """The commands build their job's options by field name (JobOptions.from_args): each field is an argument of the
    command (or, ``given``, set by the command itself), so a renamed flag cannot leave an option at its default."""
    import dataclasses
    import importlib

    from d2turb.cli import build_parser

    module, name = options.rsplit(".", 1)
    cls = getattr(importlib.import_module(module), name)
    args = build_parser().parse_args(argv)
    fields = {f.name for f in dataclasses.fields(cls)}
    assert {f for f in fields if not hasattr(args, f)} == given
    built = cls.from_args(args, **{f: getattr(cls(), f) for f in given})
    assert all(getattr(built, f) == getattr(args, f) for f in fields - given)


def test_job_options_by_keyword_as_the_old_signatures_took_them(tmp_path):
    """restore_files / restore_clip_files / clip_restorer / simulate_files take one options value; the keyword form
    of their earlier signatures still works (a keyword replaces that field of the options), an unknown keyword is a
    TypeError as it was."""
    from d2turb.data.simulate import SimulateOptions, simulate_files
    from d2turb.restore.clip_build import ClipOptions, clip_restorer
    from d2turb.restore.files import RestoreOptions, restore_files
    from d2turb.sim import TurbulenceParams

    assert RestoreOptions.of(None, tile=256) == RestoreOptions(tile=256)
    assert RestoreOptions.of(ClipOptions(tile=64, dr0=2.0), compare=True) == RestoreOptions(tile=64, compare=True)
    assert ClipOptions.of(ClipOptions(passes=3), passes=1).passes == 1
    with pytest.raises(TypeError, match="deblur"):
        RestoreOptions.of(None, deblur="none")  # a clip's option is not an image restoration's
    with pytest.raises(TypeError, match="tiles"):
        restore_files([tmp_path / "a.png"], tmp_path / "o", tiles=3)
    image = rgb(tmp_path / "a.png", 24, 32)
    assert simulate_files([image], tmp_path / "s", TurbulenceParams(dr0=2.0), seed=3, save_tilt=False) == 0
    assert sorted(p.name for p in (tmp_path / "s").iterdir()) == ["a_meta.json", "a_turb.png"]
    same = simulate_files([image], tmp_path / "t", TurbulenceParams(dr0=2.0), SimulateOptions(seed=3, save_tilt=False))
    assert same == 0 and (tmp_path / "s" / "a_turb.png").read_bytes() == (tmp_path / "t" / "a_turb.png").read_bytes()
    restorer, name, record = clip_restorer(tmp_path, 4, deblur="physics", dr0=2.0, passes=1, fusion="robust")
    assert restorer.passes == 1 and restorer.fusion == "robust" and record["dr0"] == 2.0 and name.startswith("physics")
