"""Hostile input at the command line (issue 9): every bad input is one `error:` line with a stated exit
status, folders with bad files are processed around them, outputs are readable by others, killed runs
leave nothing behind."""

import json
import math
import os
import signal
import stat
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from d2turb.cli import main
from d2turb.defaults import DEFAULT_MAX_PIXELS
from d2turb.device import DistributedEnv, distributed_env, resolve_device
from d2turb.errors import D2TurbError
from d2turb.io import (
    BackgroundWriter,
    atomic_path,
    check_output_dir,
    remove_stale_temp_files,
    write_image,
    write_json,
)

ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
ROOT = Path(__file__).resolve().parents[1]
ENV["PYTHONPATH"] = str(ROOT / "src") + os.pathsep + ENV.get("PYTHONPATH", "")


# ----------------------------------------------------------------------------------------------- helpers
def png_bomb(path: Path, width: int = 100_000, height: int = 100_000, color_type: int = 2) -> Path:
    """A 60-byte PNG whose header claims width x height pixels, RGB (colour type 2) or 8-bit grey (0) (written
    from the PNG spec's chunk layout)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", width, height, 8, color_type, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"")) + chunk(b"IEND", b"")
    )
    return path


def rgb(path: Path, h: int = 24, w: int = 32, seed: int = 0) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)).save(path)
    return path


def bad_files(folder: Path) -> dict[str, str]:
    """One file of each kind of bad input → a word its error line must contain."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really a png")
    good = rgb(folder / "tmp_source.png", 40, 40)
    data = good.read_bytes()
    good.unlink()
    (folder / "truncated.png").write_bytes(data[: len(data) // 2])
    (folder / "empty.jpg").write_bytes(b"")
    (folder / "text.png").write_text("just text")
    png_bomb(folder / "bomb.png")
    rgb(folder / "dot.png", 1, 1)
    return {
        "corrupt.png": "cannot read",
        "truncated.png": "cannot read",
        "empty.jpg": "cannot read",
        "text.png": "cannot read",
        "bomb.png": "100000x100000",
        "dot.png": "too small",
    }


def run_cli(capsys, argv):
    rc = main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


def one_error_line(err: str, *words: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("error: ") and "Traceback" not in err, err
    for word in words:
        assert word in lines[0], (word, lines[0])
    return lines[0]


def error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("error: ")]


def temp_files(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if ".tmp" in p.name]


@pytest.fixture
def tiny_weights(tmp_path_factory):
    """A tiny NAFNet whose (finite, checksummed) weights overflow to inf/NaN in its forward pass."""
    from d2turb.models import create_model, save_pretrained

    torch.manual_seed(0)
    model = create_model("nafnet", width=8, enc_blocks=[1], dec_blocks=[1])
    with torch.no_grad():
        model.backbone.intro.weight.fill_(1e30)
    path = tmp_path_factory.mktemp("weights") / "overflow.safetensors"
    save_pretrained(model, path)
    return path


def make_dataset_args(clean, out, *extra, depth="none"):
    return [
        "make-dataset",
        "--clean",
        str(clean),
        "--out",
        str(out),
        "--pairs",
        "2",
        "--patch",
        "16",
        "--batch",
        "2",
        "--depth",
        depth,
        "--device",
        "cpu",
        "--no-progress",
        *extra,
    ]


# --------------------------------------------------------------------------------- 1. decompression bombs
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


def test_make_dataset_skips_a_bomb_like_other_unreadable_sources(tmp_path, capsys):
    clean = tmp_path / "clean"
    rgb(clean / "a.png", 40, 48)
    png_bomb(clean / "b_bomb.png")
    rc, _, err = run_cli(capsys, make_dataset_args(clean, tmp_path / "ds"))
    assert rc == 0, err
    assert "b_bomb.png" in err and "100000x100000" in err and "Traceback" not in err
    meta = [json.loads(line) for line in (tmp_path / "ds" / "meta.jsonl").read_text().splitlines()]
    assert len(meta) == 2 and all(m["source"].endswith("a.png") for m in meta)


# ------------------------------------------------------------------------------------------- 2. bad --out
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


def test_write_failures_become_one_line_errors(tmp_path, monkeypatch):
    # what root or a full disk would only show at write time: the OSError becomes a D2TurbError naming the file
    monkeypatch.setattr(os, "access", lambda *a, **k: False)
    with pytest.raises(D2TurbError, match="not writable"):
        check_output_dir(tmp_path / "x")
    monkeypatch.undo()

    def refuse(path):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr("d2turb.io.atomic._open_temp", refuse)
    with pytest.raises(D2TurbError, match=r"cannot write .*a\.png: Permission denied"):
        write_image(tmp_path / "a.png", torch.rand(3, 4, 4))
    monkeypatch.undo()

    def full_disk(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", full_disk)
    with pytest.raises(D2TurbError, match=r"cannot write .*a\.json: No space left on device"):
        write_json(tmp_path / "a.json", {"a": 1})
    monkeypatch.undo()
    with pytest.raises(D2TurbError, match="cannot write"), atomic_path(tmp_path / "b.json") as tmp:
        tmp.write_text("{")
        raise OSError(28, "No space left on device")
    assert not list(tmp_path.iterdir())


def test_writer_errors_surface_in_the_command(tmp_path, capsys):
    image = rgb(tmp_path / "in" / "a.png")
    out = tmp_path / "out"
    (out / "a_turb.png").mkdir(parents=True)  # a folder where an output file must go
    rc, _, err = run_cli(capsys, ["simulate", str(image), "--out", str(out)])
    assert rc == 2
    one_error_line(err, "cannot write", "a_turb.png")
    assert not temp_files(out)


# -------------------------------------------------------------------------------------------- 3. devices
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


def test_resolve_device_rules(monkeypatch):
    assert resolve_device("cpu") == torch.device("cpu") and resolve_device(None).type in ("cpu", "cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert resolve_device("auto") == torch.device("cuda", 0)
    assert resolve_device("auto", local_rank=3) == torch.device("cuda", 1)  # ranks wrap onto the GPUs
    assert resolve_device("CUDA:1") == torch.device("cuda", 1)
    with pytest.raises(D2TurbError, match="2 GPU"):
        resolve_device("cuda:2")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == torch.device("cpu")
    with pytest.raises(D2TurbError, match="CUDA is not available"):
        resolve_device("cuda:0")


def test_distributed_environment_is_read_in_one_place(monkeypatch):
    for name in ("RANK", "WORLD_SIZE", "LOCAL_RANK"):
        monkeypatch.delenv(name, raising=False)
    assert distributed_env() == DistributedEnv(rank=0, world=1, local_rank=0)  # one process
    monkeypatch.setenv("WORLD_SIZE", "4")
    monkeypatch.setenv("RANK", "3")
    assert distributed_env() == DistributedEnv(3, 4, 3)  # LOCAL_RANK defaults to RANK (one machine)
    monkeypatch.setenv("LOCAL_RANK", "1")
    assert distributed_env() == DistributedEnv(3, 4, 1)
    monkeypatch.setenv("LOCAL_RANK", "one")
    with pytest.raises(D2TurbError, match="LOCAL_RANK must be an integer, got 'one'"):
        distributed_env()
    monkeypatch.setenv("LOCAL_RANK", "0")
    monkeypatch.setenv("RANK", "4")
    with pytest.raises(D2TurbError, match="bad distributed environment: RANK=4 WORLD_SIZE=4"):
        distributed_env()


# ---------------------------------------------------------------------------------------------- 4. seeds
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


# ---------------------------------------------------------------------------------- 5. non-finite outputs
def test_non_finite_model_output_is_refused(tiny_weights, tmp_path, capsys):
    for name in ("a", "b"):
        rgb(tmp_path / "in" / f"{name}.png", 32, 32)
    out = tmp_path / "out"
    rc, _, err = run_cli(capsys, ["restore", str(tmp_path / "in"), "--weights", str(tiny_weights), "--out", str(out)])
    assert rc == 2  # nothing could be restored
    lines = error_lines(err)
    assert len(lines) == 2 and all("NaN or infinite" in line for line in lines)
    assert "a.png" in lines[0] and "b.png" in lines[1] and "Traceback" not in err
    assert not out.exists() or not any(out.iterdir())


# ------------------------------------------------------------------------------------------------ 6. modes
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
    weights = save_pretrained(
        create_model("nafnet", width=8, enc_blocks=[1], dec_blocks=[1]), tmp_path / "w.safetensors"
    )
    assert main(["restore", str(image), "--weights", str(weights), "--out", str(tmp_path / "res")]) == 0
    capsys.readouterr()
    modes = {**_modes(tmp_path / "sim"), **_modes(tmp_path / "ds"), **_modes(tmp_path / "res")}
    modes["w.safetensors"] = stat.S_IMODE(weights.stat().st_mode)
    assert {"a_turb.png", "a_meta.json", "a_flow.npy", "dataset.json", "meta.jsonl", "a_restored.png"} <= {
        Path(k).name for k in modes
    }
    assert any(k.startswith("turb/") for k in modes) and any(k.startswith("flow/") for k in modes)
    assert set(modes.values()) == {0o644}, modes


def test_atomic_writes_follow_the_umask(tmp_path):
    old = os.umask(0o077)
    try:
        write_json(tmp_path / "private.json", {})
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "private.json").stat().st_mode) == 0o600


# -------------------------------------------------------------------------------------------- 7. temp files
def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_stale_temp_files_are_removed_live_ones_kept(tmp_path):
    dead, live = _dead_pid(), os.getppid()
    stale = [
        tmp_path / f".a_turb.png.{dead}-0123abcd.tmp.png",
        tmp_path / ".a_meta.json.k2j4_x9q.tmp.json",  # older mkstemp-style name, no pid
        tmp_path / f".last.{dead}-00ff00ff.tmp",
    ]
    kept = [
        tmp_path / f".b_turb.png.{live}-0123abcd.tmp.png",  # a process that still runs may be writing it
        tmp_path / ".notes.tmp.txt",  # not one of ours (suffix does not match the name's)
        tmp_path / "a_turb.png",
    ]
    for p in stale + kept:
        p.write_bytes(b"")
    nested = tmp_path / "clip" / stale[0].name  # grids/<folder>/ of evaluate --real --recursive
    nested.parent.mkdir()
    nested.write_bytes(b"")
    assert remove_stale_temp_files(tmp_path) == len(stale)
    assert sorted(tmp_path.iterdir()) == sorted([*kept, nested.parent]) and nested.exists()
    assert remove_stale_temp_files(tmp_path, recursive=True) == 1 and not nested.exists()
    assert sorted(tmp_path.iterdir()) == sorted([*kept, nested.parent])


def test_rerun_removes_temp_files_a_kill_left(tmp_path, capsys):
    image = rgb(tmp_path / "in" / "a.png")
    out = tmp_path / "out"
    out.mkdir()
    leftover = out / f".a_turb.png.{_dead_pid()}-deadbeef.tmp.png"
    leftover.write_bytes(b"")
    assert main(["simulate", str(image), "--out", str(out)]) == 0
    assert not temp_files(out) and (out / "a_turb.png").is_file()


# ------------------------------------------------------------------------------------ 8. failed make-dataset
def test_failed_make_dataset_does_not_lock_the_folder(tmp_path, capsys):
    clean = tmp_path / "clean"
    rgb(clean / "a.png", 40, 48)
    (tmp_path / "no_maps").mkdir()
    out = tmp_path / "ds"
    rc, _, err = run_cli(capsys, make_dataset_args(clean, out, depth=str(tmp_path / "no_maps")))
    assert rc == 2
    one_error_line(err, "no depth file")
    assert not (out / "dataset.json").exists()
    assert main(make_dataset_args(clean, out)) == 0  # the corrected run, same --out
    # a config left by a run killed before its first sample does not lock the folder either
    killed = tmp_path / "killed"
    assert main(make_dataset_args(clean, killed, "--seed", "5")) == 0
    (killed / "meta.jsonl").unlink()  # as if killed before any sample's meta line was written
    (killed / "turb" / "0000000.png").unlink()
    assert main(make_dataset_args(clean, killed)) == 0
    assert json.loads((killed / "dataset.json").read_text())["seed"] == 0
    assert main(["check-dataset", str(killed)]) == 0
    capsys.readouterr()


# --------------------------------------------------------------------------------------- 9. same stems
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


# ------------------------------------------------------------------------------ 10. folders with bad files
def test_simulate_folder_with_bad_files(tmp_path, capsys):
    folder = tmp_path / "in"
    bad = bad_files(folder)
    good = ["g1", "g2", "g3"]
    for i, name in enumerate(good):
        rgb(folder / f"{name}.png", 24, 32 if i < 2 else 20, seed=i)  # two sizes: two batches
    out = tmp_path / "out"
    rc, stdout, err = run_cli(capsys, ["simulate", str(folder), "--out", str(out), "--no-tilt"])
    assert rc == 1
    lines = error_lines(err)
    assert len(lines) == len(bad)
    for name, word in bad.items():
        assert any(name in line and word in line for line in lines), (name, lines)
    assert f"3 of {len(bad) + 3} inputs done, {len(bad)} failed" in err
    assert sorted(p.name for p in out.iterdir()) == sorted(f"{n}_{k}" for n in good for k in ("turb.png", "meta.json"))
    # --fail-fast: the first bad file (sorted order: bomb.png) ends the run in one line
    rc, _, err = run_cli(capsys, ["simulate", str(folder), "--out", str(tmp_path / "ff"), "--fail-fast"])
    assert rc == 2
    one_error_line(err, "bomb.png")


def test_restore_folder_with_each_kind_of_bad_file_then_sigkill_and_rerun(tmp_path, capsys):
    """Acceptance 2: every good output, one error line per bad file, non-zero exit; then a run killed by
    SIGKILL and re-run finishes cleanly with no temp files left."""
    folder = tmp_path / "in"
    bad = bad_files(folder)
    good = [f"g{i}" for i in range(4)]
    for i, name in enumerate(good):
        rgb(folder / f"{name}.png", 300, 400, seed=i)  # noise: slow to compress, so writes take a while
    out = tmp_path / "out"
    argv = ["restore", str(folder), "--weights", "input", "--out"]
    rc, _, err = run_cli(capsys, [*argv, str(out)])
    assert rc == 1
    lines = error_lines(err)
    assert len(lines) == len(bad), err
    for name, word in bad.items():
        assert any(name in line and word in line for line in lines), (name, lines)
    assert "Traceback" not in err and f"restore: 4 of {len(bad) + 4} inputs done" in err
    assert sorted(p.name for p in out.iterdir()) == sorted(f"{n}_restored.png" for n in good)
    reference = {p.name: p.read_bytes() for p in out.iterdir()}

    killed = tmp_path / "killed"
    cmd = [sys.executable, "-m", "d2turb", *argv, str(killed), "--png-compression", "9"]
    proc = subprocess.Popen(cmd, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None and not (killed.is_dir() and any(killed.iterdir())):
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    assert proc.wait() == -signal.SIGKILL, "the run finished before it could be killed"
    rc, _, err = run_cli(capsys, [*argv, str(killed)])
    assert rc == 1 and len(error_lines(err)) == len(bad), err
    assert not temp_files(killed)
    assert {p.name: p.read_bytes() for p in killed.iterdir()} == reference


def test_evaluate_real_folder_with_bad_files_lists_them(tmp_path, capsys, astronaut):
    folder = tmp_path / "real"
    write_image(folder / "a.png", astronaut[0, :, :192, :160])
    write_image(folder / "b.png", astronaut[0, :, 40:, 30:])
    (folder / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\nno")
    png_bomb(folder / "bomb.png")
    out = tmp_path / "out"
    rc, _, err = run_cli(capsys, ["evaluate", "--real", str(folder), "--metrics", "piqe", "--out", str(out)])
    assert rc == 1
    lines = error_lines(err)
    assert len(lines) == 2 and "bomb.png" in lines[0] and "corrupt.png" in lines[1]
    results = json.loads((out / "results.json").read_text())
    assert results["images"] == ["a.png", "b.png"]
    assert [s["file"] for s in results["skipped"]] == ["bomb.png", "corrupt.png"]
    assert set(results["piqe"]["per_image"]) == {"a.png", "b.png"}
    assert "corrupt.png" in (out / "results.md").read_text()


def test_evaluate_data_skips_a_broken_sample(tmp_path, capsys):
    root = tmp_path / "ds"
    meta = []
    for i in range(3):
        sid = f"{i:07d}"
        image = torch.rand(3, 16, 16, generator=torch.Generator().manual_seed(i))
        for kind in ("turb", "tilt", "gt"):
            write_image(root / kind / f"{sid}.png", image)
        write_image(root / "depth" / f"{sid}.png", image[:1])
        (root / "flow").mkdir(exist_ok=True)
        np.save(root / "flow" / f"{sid}.npy", np.zeros((2, 16, 16), np.float16))
        meta.append({"id": sid, "index": i, "dr0": 3.0, "bin": "medium", "split": "test"})
    (root / "meta.jsonl").write_text("".join(json.dumps(m) + "\n" for m in meta))
    (root / "dataset.json").write_text(json.dumps({"version": 1, "pairs": 3, "patch": 16, "split": "test"}))
    (root / "turb" / "0000001.png").write_bytes(b"\x89PNG\r\n\x1a\ncut")
    out = tmp_path / "out"
    rc, _, err = run_cli(
        capsys, ["evaluate", "--data", str(root), "--weights", "input", "--metrics", "psnr", "--out", str(out)]
    )
    assert rc == 1
    lines = error_lines(err)
    assert len(lines) == 1 and "0000001" in lines[0]
    results = json.loads((out / "results.json").read_text())
    assert results["samples_evaluated"] == 2 and [s["id"] for s in results["skipped"]] == ["0000001"]


# ------------------------------------------------------------------------------------------------ 11. minor
def test_check_dataset_with_null_bin_ranges(tmp_path, capsys):
    (tmp_path / "dataset.json").write_text(json.dumps({"pairs": 1, "patch": 16, "bin_ranges": None}))
    rc, _, err = run_cli(capsys, ["check-dataset", str(tmp_path)])
    assert rc == 2
    one_error_line(err, "dataset.json", "bin_ranges")


def test_patch_larger_than_every_source_is_refused(tmp_path, capsys):
    clean = tmp_path / "clean"
    rgb(clean / "a.png", 96, 96)
    rgb(clean / "b.png", 64, 90)
    argv = make_dataset_args(clean, tmp_path / "ds")
    argv[argv.index("--patch") + 1] = "4096"
    rc, _, err = run_cli(capsys, argv)
    assert rc == 2
    one_error_line(err, "--patch 4096", "96 px")
    assert not (tmp_path / "ds").exists()


def test_small_sources_are_reported(tmp_path, capsys):
    clean = tmp_path / "clean"
    rgb(clean / "a.png", 40, 48)
    rgb(clean / "b.png", 12, 14)
    rc, _, err = run_cli(capsys, make_dataset_args(clean, tmp_path / "ds", "--split", "train", "--pairs", "6"))
    assert rc == 0
    assert err.count("b.png is 14x12, smaller than the 16-px patch: resized up") == 1


def test_depth_map_of_another_aspect_is_refused(tmp_path, capsys):
    image = rgb(tmp_path / "a.png", 24, 32)
    np.save(tmp_path / "depth.npy", np.ones((24, 24)))
    rc, _, err = run_cli(
        capsys, ["simulate", str(image), "--out", str(tmp_path / "o"), "--depth", str(tmp_path / "depth.npy")]
    )
    assert rc == 2
    one_error_line(err, "depth.npy", "24x24", "32x24", "aspect")
    assert not (tmp_path / "o").exists()
    np.save(tmp_path / "depth.npy", np.ones((12, 16)))  # same aspect, other resolution: resized
    assert main(["simulate", str(image), "--out", str(tmp_path / "o"), "--depth", str(tmp_path / "depth.npy")]) == 0


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


def test_interrupted_line_is_not_inside_the_progress_bar(tmp_path, capsys, monkeypatch):
    from d2turb.restore import Restorer

    for i in range(3):
        rgb(tmp_path / "in" / f"{i}.png", seed=i)
    calls = []
    original = Restorer.restore_with_details

    def interrupt_second(self, image):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return original(self, image)

    monkeypatch.setattr(Restorer, "restore_with_details", interrupt_second)
    rc, _, err = run_cli(capsys, ["restore", str(tmp_path / "in"), "--weights", "input", "--out", str(tmp_path / "o")])
    assert rc == 130
    assert "restore:" in err  # the bar was drawn
    assert err.split("\n")[-2] == "interrupted", repr(err[-200:])
    assert not temp_files(tmp_path / "o")


# ------------------------------------------------------------------------------------- background writer
def test_background_writer_surfaces_errors_and_bounds_the_queue(tmp_path):
    import threading

    gate = threading.Event()
    done = []
    writer = BackgroundWriter(max_pending=2, threads=1)
    writer.submit(gate.wait)
    writer.submit(done.append, 1)
    writer.submit(done.append, 2)  # queue full now: the next submit would block until the gate opens
    gate.set()
    writer.submit(lambda: (_ for _ in ()).throw(D2TurbError("disk on fire")))
    writer.submit(done.append, 3)  # dropped or run: the error is reported either way
    with pytest.raises(D2TurbError, match="disk on fire"):
        for _ in range(100):
            writer.submit(done.append, 4)
            time.sleep(0.01)
        writer.close()
    assert done[:2] == [1, 2]
    with BackgroundWriter() as w:  # a clean run writes everything
        for i in range(5):
            w.submit(write_json, tmp_path / f"{i}.json", {"i": i})
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"{i}.json" for i in range(5)]


def test_phased_writer_finishes_the_queued_writes_before_each_computation():
    import threading

    gate, done = threading.Event(), []

    def slow(i):
        gate.wait(30)
        done.append(i)

    from d2turb.device import usable_cores

    cores = usable_cores()
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(cores)
        with BackgroundWriter(compute_device="cuda", threads=1) as writer:  # a GPU computation: writes overlap it
            writer.submit(slow, 0)
            writer.before_compute()
            assert done == [] and not writer.phased
            gate.set()
        assert done == [0]
        gate.clear()
        with BackgroundWriter(compute_device="cpu", threads=2) as writer:  # every core computing: writes first
            assert writer.phased
            for i in range(1, 5):
                writer.submit(slow, i)
            threading.Timer(0.05, gate.set).start()
            writer.before_compute()
            assert sorted(done) == [0, 1, 2, 3, 4]
        if cores > 1:  # a core left free for the writer: overlap
            torch.set_num_threads(cores - 1)
            with BackgroundWriter(compute_device="cpu") as writer:
                assert not writer.phased
        torch.set_num_threads(cores)
        writer = BackgroundWriter(compute_device="cpu")
    finally:
        torch.set_num_threads(threads)
    writer.submit(lambda: (_ for _ in ()).throw(D2TurbError("disk on fire")))
    with pytest.raises(D2TurbError, match="disk on fire"):
        writer.before_compute()
    with pytest.raises(D2TurbError, match="disk on fire"):  # sticky: close reports it too
        writer.close()


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="counts threads in /proc")
def test_background_writes_start_no_compute_threads(tmp_path):
    """Writers convert tensors with numpy: a torch operator in a writer thread would start an OpenMP team of
    its own, and more compute threads than cores slow the main computation. The only new thread is the writer."""
    import threading

    from d2turb.data.layout import write_depth_png

    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        image = torch.rand(3, 256, 256)
        image.clamp(0, 1)  # this thread's own team exists before counting
        before = set(os.listdir("/proc/self/task"))
        written = threading.Event()
        with BackgroundWriter(threads=1) as writer:
            writer.submit(write_image, tmp_path / "a.png", image)
            writer.submit(write_depth_png, tmp_path / "d.png", image[:1])
            writer.submit(written.set)
            assert written.wait(60)
            # threads started meanwhile (a thread of an earlier test, e.g. tqdm's monitor, may end: not counted)
            started = set(os.listdir("/proc/self/task")) - before
            assert len(started) == 1, started
    finally:
        torch.set_num_threads(threads)
