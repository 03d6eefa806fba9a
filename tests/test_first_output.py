"""The first minute of make-dataset and simulate-video (issue 26, item 6): what they wait for is said before the
first output, the bar's estimate is timed on whole chunks, and the commands that run the simulator on a CPU ask
OpenMP to sleep rather than spin while it waits (no timing is asserted here: benchmarks/bench_first_output.py)."""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest
import tqdm as tqdm_module
from PIL import Image

from d2turb.cli import build_parser, main
from d2turb.commands.common import apply_wait_policy


def _clean(folder, n=2, size=(40, 48)):
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(n):
        Image.fromarray(rng.integers(0, 256, (*size, 3), dtype=np.uint8)).save(folder / f"{i}.png")
    return folder


class _RecordingBar(tqdm_module.tqdm):
    """tqdm that records (event, count so far, text) for each update and postfix."""

    events: list = []

    def update(self, n=1):
        type(self).events.append(("update", n, ""))
        return super().update(n)

    def set_postfix_str(self, s="", refresh=True):
        type(self).events.append(("phase", self.n, s))
        return super().set_postfix_str(s, refresh)


def test_make_dataset_says_what_the_first_chunk_waits_for_and_counts_chunks(tmp_path, monkeypatch, capsys):
    """Before the first pair the bar names the phases (simulator, sources + depth, the batch's simulation); pairs
    are counted a chunk at a time (a per-pair step timed one pair for a whole chunk, so the first estimate was
    `--batch` times too long); the files are those of a run without the bar."""
    _RecordingBar.events = []
    monkeypatch.setattr(tqdm_module, "tqdm", _RecordingBar)
    clean = _clean(tmp_path / "clean")
    argv = ["make-dataset", "--clean", str(clean), "--pairs", "5", "--patch", "16", "--batch", "2", "--device", "cpu"]
    assert main([*argv, "--out", str(tmp_path / "bar")]) == 0
    events = _RecordingBar.events
    assert [n for kind, n, _ in events if kind == "update"] == [2, 2, 1]
    first_update = next(i for i, e in enumerate(events) if e[0] == "update")
    before = " | ".join(text for kind, n, text in events[:first_update] if kind == "phase" and n == 0)
    for words in ("setting up the simulator", "reading source images + depth (prior)", "simulating 2 pairs"):
        assert words in before
    capsys.readouterr()

    assert main([*argv, "--out", str(tmp_path / "quiet"), "--no-progress"]) == 0
    assert "simulating" not in capsys.readouterr().err  # --no-progress: no bar, no phases
    files = sorted(p.relative_to(tmp_path / "bar") for p in (tmp_path / "bar").rglob("*") if p.is_file())
    assert len(files) > 10
    for rel in files:
        assert (tmp_path / "bar" / rel).read_bytes() == (tmp_path / "quiet" / rel).read_bytes(), rel


def test_simulate_video_says_what_it_does_before_the_first_frame(tmp_path, monkeypatch, capsys):
    """The line naming the frames, size, D/r0 and depth comes before the first frame file is written."""
    import d2turb.data.simulate as job  # the simulate-video job writes the frames (the command parses, then calls it)

    image = tmp_path / "photo.png"
    Image.fromarray(np.random.default_rng(1).integers(0, 256, (24, 32, 3), dtype=np.uint8)).save(image)
    write_image = job.write_image
    seen = []

    def marked(path, *args, **kwargs):
        if not seen:
            seen.append(path)
            print("<first frame written>", file=sys.stderr)
        return write_image(path, *args, **kwargs)

    monkeypatch.setattr(job, "write_image", marked)
    argv = ["simulate-video", str(image), "--out", str(tmp_path / "out"), "--frames", "2", "--no-mp4"]
    assert main([*argv, "--device", "cpu"]) == 0
    err = capsys.readouterr().err
    assert seen and seen[0].name == "000000.png"
    banner = err.index("photo.png: simulating 2 frames of 32x24 at D/r0 = 3 (depth: prior, once)")
    assert banner < err.index("<first frame written>")
    assert "the bar's time estimate follows the first one" in err


@pytest.fixture
def no_wait_policy(monkeypatch):
    """No OMP_WAIT_POLICY, and torch not yet loaded as far as apply_wait_policy can tell (both restored after)."""
    monkeypatch.setenv("OMP_WAIT_POLICY", "unset-by-the-test")  # recorded, so the variable is restored afterwards
    monkeypatch.delenv("OMP_WAIT_POLICY")
    monkeypatch.delitem(sys.modules, "torch")


@pytest.mark.parametrize(
    "command",
    [
        ["make-dataset", "--clean", "c", "--out", "o", "--pairs", "1"],
        ["simulate-video", "x", "--out", "o"],
        ["restore", "clip", "--temporal", "8", "--out", "o"],
    ],
)
def test_simulator_commands_wait_passively(command, no_wait_policy, monkeypatch):
    """make-dataset, simulate-video and clip restoration set OMP_WAIT_POLICY=PASSIVE before torch would load OpenMP;
    a policy the user set is kept; other commands are left as they were."""
    apply_wait_policy(build_parser().parse_args(command))
    assert os.environ["OMP_WAIT_POLICY"] == "PASSIVE"
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    apply_wait_policy(build_parser().parse_args(command))
    assert os.environ["OMP_WAIT_POLICY"] == "ACTIVE"


@pytest.mark.parametrize("command", [["simulate", "x", "--out", "o"], ["restore", "x.png", "--out", "o"]])
def test_other_commands_keep_the_openmp_default(command, no_wait_policy):
    apply_wait_policy(build_parser().parse_args(command))
    assert "OMP_WAIT_POLICY" not in os.environ


def test_wait_policy_left_alone_once_torch_is_loaded(no_wait_policy, monkeypatch):
    """main() called in a process that already imported torch: too late for OpenMP, the environment is kept."""
    monkeypatch.setitem(sys.modules, "torch", object())
    apply_wait_policy(build_parser().parse_args(["simulate-video", "x", "--out", "o"]))
    assert "OMP_WAIT_POLICY" not in os.environ


def test_the_policy_is_in_place_when_torch_loads(tmp_path):
    """In a fresh process (as the console script runs), main() sets the policy before anything imports torch."""
    import subprocess
    from pathlib import Path

    src = str(Path(__file__).resolve().parents[1] / "src")
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    env.update(OMP_NUM_THREADS="1", PYTHONPATH=src + os.pathsep + os.environ.get("PYTHONPATH", ""))
    probe = (
        "import os, sys\n"
        "from d2turb.cli import main\n"
        "seen = []\n"
        "class Finder:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name == 'torch' and not seen:\n"
        "            seen.append(os.environ.get('OMP_WAIT_POLICY'))\n"
        "sys.meta_path.insert(0, Finder())\n"
        f"rc = main(['simulate-video', {str(tmp_path / 'missing.png')!r}, '--out', {str(tmp_path / 'out')!r}])\n"
        "print(rc, seen)\n"
    )
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, timeout=300)
    assert out.stdout.split() == ["2", "['PASSIVE']"], out.stderr
