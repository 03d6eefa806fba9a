"""d2turb.io.atomic: writes that fail become one-line errors, follow the umask, and leave no temp file; temp
names fit wherever the name does, and those a killed run left are removed."""

import os
import stat
from pathlib import Path

import pytest
import torch
from hostile_input import dead_pid, rgb, run_cli
from PIL import Image

from d2turb.errors import D2TurbError
from d2turb.io import atomic_path, check_output_dir, remove_stale_temp_files, write_image, write_json


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


def test_atomic_writes_follow_the_umask(tmp_path):
    old = os.umask(0o077)
    try:
        write_json(tmp_path / "private.json", {})
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "private.json").stat().st_mode) == 0o600


def test_stale_temp_files_are_removed_live_ones_kept(tmp_path):
    dead, live = dead_pid(), os.getppid()
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


def test_outputs_with_the_longest_legal_names_are_written(tmp_path, capsys):
    stem = "é" + "x" * 234  # 236 bytes: NAME_meta.json is 250 bytes, within the 255 a file name may have
    image = rgb(tmp_path / "in" / f"{stem}.png", 24, 32)
    out = tmp_path / "out"
    out.mkdir()
    leftover = out / f".{stem[:200]}.png.{dead_pid()}-deadbeef.tmp.png"  # a cut temp name of a killed run
    leftover.write_bytes(b"")
    rc, _, err = run_cli(capsys, ["simulate", str(image), "--out", str(out)])
    assert rc == 0, err
    assert sorted(p.name for p in out.iterdir()) == sorted(f"{stem}_{k}" for k in ("turb.png", "tilt.png", "meta.json"))
    assert Image.open(out / f"{stem}_turb.png").size == (32, 24)


def test_temp_names_fit_whenever_the_name_does():
    from d2turb.io import temp_name

    for name in ("a.png", "x" * 251 + ".png", "é" * 125 + ".json", "y" * 255, "z" * 248 + ".tar.gz"):
        assert len(name.encode()) <= 255
        tmp = temp_name(name, f"{2**22}-0123abcd")
        assert (
            len(tmp.encode()) <= 255
            and tmp.startswith(".")
            and tmp.endswith(f".{2**22}-0123abcd.tmp{Path(name).suffix}")
        )
        tmp.encode().decode()  # cut at a character boundary
    # a name that is not UTF-8 (raw bytes, surrogate-escaped by Python) is counted and kept in bytes (issue 37)
    for raw in (b"\xff\xfe.png", b"\xe9" * 251 + b".png"):
        tmp = temp_name(os.fsdecode(raw), "1-0123abcd")
        assert len(os.fsencode(tmp)) <= 255 and os.fsencode(tmp).startswith(b"." + raw[:8])
