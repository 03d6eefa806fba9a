"""Hostile input at the command line, round 2 (issue 25): no crash by signal, nothing read outside a dataset,
no user file overwritten, one `error:` line instead of a traceback, no quiet wrong output."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from d2turb.cli import main

ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
ROOT = Path(__file__).resolve().parents[1]
ENV["PYTHONPATH"] = str(ROOT / "src") + os.pathsep + ENV.get("PYTHONPATH", "")


# ----------------------------------------------------------------------------------------------- helpers
def rgb(path: Path, h: int = 24, w: int = 32, seed: int = 0) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)).save(path)
    return path


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


def run_d2turb(*args, timeout: float = 300, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "d2turb", *map(str, args)],
        env=ENV,
        capture_output=True,
        text=True,
        timeout=timeout,
        **kwargs,
    )


# ------------------------------------------------------------------------------- 1. no crash by a signal
@pytest.mark.parametrize("size", [(3, 200), (5, 128)])
def test_simulate_a_few_pixels_high_exits_normally(size, tmp_path):
    image = rgb(tmp_path / "strip.png", *size)
    proc = run_d2turb("simulate", image, "--out", tmp_path / "out")
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-2000:])  # a signal would be negative
    assert Image.open(tmp_path / "out" / "strip_turb.png").size == (size[1], size[0])


def test_every_fft_of_the_simulator_gets_a_contiguous_tensor(tmp_path, monkeypatch, capsys):
    """The abort came from torch.fft.fft2 on the permuted view einsum returns: every FFT input in d2turb.sim
    must be contiguous (checked on the calls themselves, in simulate and simulate-video)."""
    seen = []
    for name in ("fft2", "ifft2", "rfft2", "irfft2", "fftn", "ifftn", "rfftn", "irfftn"):
        original = getattr(torch.fft, name)

        def spy(x, *args, _original=original, _name=name, **kwargs):
            seen.append((_name, tuple(x.shape), x.is_contiguous()))
            return _original(x, *args, **kwargs)

        monkeypatch.setattr(torch.fft, name, spy)
    image = rgb(tmp_path / "strip.png", 3, 200)
    assert main(["simulate", str(image), "--out", str(tmp_path / "a")]) == 0
    image = rgb(tmp_path / "b.png", 24, 40)
    assert main(["simulate", str(image), str(tmp_path / "strip.png"), "--out", str(tmp_path / "b")]) == 0
    args = ["simulate-video", str(image), "--out", str(tmp_path / "v"), "--frames", "2", "--no-mp4"]
    assert main(args) == 0
    capsys.readouterr()
    assert seen and all(contiguous for _, _, contiguous in seen), [s for s in seen if not s[2]]
