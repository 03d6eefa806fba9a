"""The first minute of make-dataset and simulate-video (issue 26, item 6): what they wait for is said before the
first output, and the bar's estimate is timed on whole chunks (no timing is asserted here)."""

from __future__ import annotations

import numpy as np
import tqdm as tqdm_module
from PIL import Image

from d2turb.cli import main


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
