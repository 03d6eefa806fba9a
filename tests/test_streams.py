"""Clips as streams (issue 52 item 2): the mp4 writer's bytes, a clip piped in or read from a local process, frames
written as they come, --max-frames, and an interrupted run's mp4."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"

_ENCODE = """
import sys
from d2turb.video import Mp4Writer
y, x = np.mgrid[0:48, 0:56].astype(np.float32)
rng = np.random.default_rng(0)
with Mp4Writer(sys.argv[1], 30.0) as w:
    for i in range(32):
        grey = 128 + 60 * np.sin(x / 5 + 0.3 * i) * np.cos(y / 7 - 0.2 * i) + rng.normal(0, 4, x.shape)
        w.write(np.clip(np.stack([grey, 0.9 * grey, 0.8 * grey], -1), 0, 255).astype(np.uint8))
"""


def test_mp4_writer_gives_the_same_bytes_whatever_the_heap_held(tmp_path):
    """x264's AVX-512 code read memory it had not written: the same frames gave different files as the heap's
    leftovers differed (glibc's MALLOC_PERTURB_ fills them with a chosen byte; the page's run and its command line's
    rerun differed so). The writer's files must not depend on it."""
    pytest.importorskip("av")
    digests = set()
    for perturb in ("0", "77", "165"):
        out = tmp_path / f"clip_{perturb}.mp4"
        env = {**os.environ, "PYTHONPATH": str(SRC), "MALLOC_PERTURB_": perturb}
        subprocess.run([sys.executable, "-c", _ENCODE, str(out)], env=env, check=True, timeout=120)
        digests.add(hashlib.sha256(out.read_bytes()).hexdigest())
    assert len(digests) == 1
