"""Helpers of the tests of hostile input at the command line (issues 9 and 25): bad files to feed the commands,
one run of the command line in this process or in a child, and the checks of its `error:` lines. The tests
themselves stand in the test file of the module each one tests."""

import json
import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
from _tiny_models import TINY_NAFNET  # noqa: F401 - the tests of hostile input import it from here
from PIL import Image

from d2turb.cli import main

# the environment of a child `python -m d2turb`: one thread, unbuffered, this checkout's d2turb
CHILD_ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
CHILD_ENV["PYTHONPATH"] = (
    str(Path(__file__).resolve().parents[1] / "src") + os.pathsep + CHILD_ENV.get("PYTHONPATH", "")
)


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


def run_d2turb(*args, timeout: float = 300, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "d2turb", *map(str, args)],
        env=CHILD_ENV,
        capture_output=True,
        text=True,
        timeout=timeout,
        **kwargs,
    )


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


# A child `python -m d2turb ARGS` that SIGKILLs itself just before its K-th file rename. Every atomic write of
# d2turb.io (write_bytes, atomic_path) ends in one os.replace of a complete temporary file, so the child dies with
# that file written under its temporary name and the files before it in place: part-way through a sample, at the
# same point whatever the machine's load. (A kill timed from outside, once some meta lines are on disk, lands
# wherever a busy machine has let the child get to.)
_KILL_AT_RENAME = """
import os, signal, sys, threading
kill_at, lock, calls, replace = int(sys.argv[1]), threading.Lock(), [0], os.replace
def counted_replace(src, dst, **kwargs):
    with lock:
        calls[0] += 1
        if calls[0] == kill_at:
            os.kill(os.getpid(), signal.SIGKILL)
    return replace(src, dst, **kwargs)
os.replace = counted_replace
from d2turb.cli import main
sys.exit(main(sys.argv[2:]))
"""


def run_killed_at_rename(kill_at: int, args, env=None, timeout: float = 300) -> subprocess.CompletedProcess:
    """Run ``d2turb ARGS`` in a child that SIGKILLs itself just before its ``kill_at``-th file rename; returns the
    finished process (returncode -SIGKILL when it got that far)."""
    cmd = [sys.executable, "-c", _KILL_AT_RENAME, str(kill_at), *map(str, args)]
    return subprocess.run(cmd, env=env or CHILD_ENV, capture_output=True, text=True, timeout=timeout)


def dead_pid() -> int:
    """The id of a process that has ended."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


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


def tiny_pairs(root: Path, n: int = 4, size: int = 32, split: str = "train") -> Path:
    """A make-dataset folder written by hand from its documented layout (docs/data.md): random images, zero flow."""
    rng = np.random.default_rng(0)
    lines = []
    for i in range(n):
        sid = f"{i:07d}"
        for kind in ("turb", "tilt", "gt"):
            rgb(root / kind / f"{sid}.png", size, size, seed=i)
        (root / "depth").mkdir(exist_ok=True)
        Image.fromarray(rng.integers(0, 65535, (size, size), dtype=np.uint16)).save(root / "depth" / f"{sid}.png")
        (root / "bwd_flow_px").mkdir(exist_ok=True)
        np.save(root / "bwd_flow_px" / f"{sid}.npy", np.zeros((2, size, size), np.float16))
        lines.append(json.dumps({"id": sid, "index": i, "dr0": 2.0, "bin": "weak", "split": split}))
    config = {"version": 1, "pairs": n, "patch": size, "split": split, "bin_ranges": {"weak": [1.0, 2.25]}}
    (root / "dataset.json").write_text(json.dumps(config))
    (root / "meta.jsonl").write_text("\n".join(lines) + "\n")
    return root


def tiny_config(tmp_path: Path, **train) -> Path:
    import yaml
    from test_train import TINY_MODEL  # here: test_train imports this module

    cfg = {
        "model": TINY_MODEL,
        "data": {"pairs": str(tiny_pairs(tmp_path / "pairs")), "patch": 32, "num_workers": 0, "hflip": False},
        "train": {"iterations": 6, "batch": 2, "lr": 1e-3, "device": "cpu", **train},
        "loss": {"vgg": 0.0},
        "log": {"every": 1, "progress": False},
        "checkpoint": {"every": 1000},
    }
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path
