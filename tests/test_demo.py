"""`d2turb demo` end to end with the shipped model (one run): the figure holds the written PNGs in
labelled cells and stays within 2000 px, the printed per-bin PSNR of the input, the clip restoration and the
single-frame model is recomputed here from those PNGs with numpy, the clip restoration visibly gains in every bin,
and the README's sentences about the demo state what it prints."""

import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from d2turb.cli import main
from d2turb.commands import demo
from d2turb.data.samples import sample_images
from d2turb.models.hub import RECOMMENDED_WEIGHTS

README = Path(__file__).resolve().parents[1] / "README.md"
LEVELS = ("weak", "medium", "strong")


@pytest.mark.slow
def test_demo_end_to_end(tmp_path, capsys):
    """One demo run (about a minute of CPU), three checks; one test, so that xdist runs the demo once."""
    out = tmp_path / "demo_out"
    assert main(["demo", "--out", str(out)]) == 0
    run = (out, capsys.readouterr().out)
    check_figure_shows_every_part(run)
    check_printed_psnr_is_what_the_pngs_give(run)
    check_readme_describes_what_the_demo_prints(run)


def _png(path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"))


def _psnr(png: np.ndarray, clean: np.ndarray) -> float:
    """PSNR (peak 1) of an 8-bit image against a float one in [0, 1]."""
    mse = np.mean((png.astype(np.float64) / 255 - clean) ** 2)
    return 10 * np.log10(1.0 / mse)


def _find(picture: np.ndarray, panel: np.ndarray) -> list[tuple[int, int]]:
    """Every (y, x) where ``panel`` sits exactly in ``picture``."""
    h, w = panel.shape[:2]
    ys, xs = np.nonzero((picture[: picture.shape[0] - h + 1, : picture.shape[1] - w + 1] == panel[0, 0]).all(axis=2))
    return [(y, x) for y, x in zip(ys, xs) if np.array_equal(picture[y : y + h, x : x + w], panel)]


def _table(printed: str, heading: str) -> dict[str, list[float]]:
    """The rows of the markdown table under ``heading``: bin → its numbers."""
    section = printed.split(heading, 1)[1]
    rows = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if cells[0] in LEVELS and cells[0] not in rows:
            rows[cells[0]] = [float(c) for c in cells[1:]]
    return rows


def _clip_scores(out: Path) -> dict[str, dict[str, float]]:
    """Per bin, the mean PSNR of input, clip and model over the scored frames, from the PNGs (numpy)."""
    clean = sample_images()[demo.CLIP_IMAGE].numpy().transpose(1, 2, 0).astype(np.float64)
    frames = range(0, demo.CLIP_FRAMES, demo.CLIP_STRIDE)
    return {
        level: {
            kind: float(np.mean([_psnr(_png(out / f"clip_{level}_{t:02d}_{kind}.png"), clean) for t in frames]))
            for kind in ("input", "clip", "model")
        }
        for level in LEVELS
    }


def check_figure_shows_every_part(demo_run):
    out, printed = demo_run
    figure = _png(out / "demo.png")
    assert max(figure.shape[:2]) <= 2000
    names = list(sample_images())
    ink = figure.min(axis=2) < 100  # dark label text on the white background
    # section 1: each simulated frame in its cell, once; row labels left of the rows, column labels above
    for name in names:
        for level in LEVELS:
            (y, x), *more = _find(figure, _png(out / f"{name}_{level}_turb.png"))
            assert not more
            assert ink[y : y + 192, :160].sum() > 20, f"no row label beside {name}"
            assert ink[y - 20 : y, x : x + 256].sum() > 10 or name != names[0], f"no column label above {level}"
    # section 2: per bin the middle frame of the clip, restored by the clip pipeline and by the model, side by side
    middle = demo.CLIP_FRAMES // 2
    for level in LEVELS:
        cells = [_find(figure, _png(out / f"clip_{level}_{middle:02d}_{k}.png")) for k in ("input", "clip", "model")]
        assert all(len(c) == 1 for c in cells), level
        (y0, x0), (y1, x1), (y2, x2) = (c[0] for c in cells)
        assert y0 == y1 == y2 and x0 < x1 < x2
        assert ink[y0 : y0 + 192, :160].sum() > 50  # the bin's label with its PSNR lines
    assert Image.open(out / "demo_clip.gif").n_frames == demo.CLIP_FRAMES


def check_printed_psnr_is_what_the_pngs_give(demo_run):
    out, printed = demo_run
    table = _table(printed, "## A clip")
    scores = _clip_scores(out)
    for level in LEVELS:
        dr0, p_in, p_clip, gain, p_model, gain_model = table[level][:6]
        assert p_in == pytest.approx(scores[level]["input"], abs=0.006)
        assert p_clip == pytest.approx(scores[level]["clip"], abs=0.006)
        assert p_model == pytest.approx(scores[level]["model"], abs=0.006)
        assert gain == pytest.approx(p_clip - p_in, abs=0.011) and gain_model == pytest.approx(
            p_model - p_in, abs=0.011
        )
        # the clip pipeline visibly removes turbulence: at least 1 dB over the input in every bin, above the model
        assert scores[level]["clip"] > scores[level]["input"] + 1.0 and scores[level]["clip"] > scores[level]["model"]
    assert "## Single frames" in printed and RECOMMENDED_WEIGHTS in printed


def check_readme_describes_what_the_demo_prints(demo_run):
    """Every number the README quotes for the demo is the demo's (to the README's one decimal)."""
    _, printed = demo_run
    text = README.read_text()
    quoted = re.search(r"clip pipeline gains ([+-][\d.]+) / ([+-][\d.]+) / ([+-][\d.]+) dB", text)
    model = re.search(r"single-frame model ([+-][\d.]+) / ([+-][\d.]+) / ([+-][\d.]+) dB", text)
    assert quoted and model, "the README's demo sentence is missing"
    clip = _table(printed, "## A clip")
    for k, level in enumerate(LEVELS):
        assert float(quoted.group(k + 1)) == pytest.approx(clip[level][3], abs=0.051)
        assert float(model.group(k + 1)) == pytest.approx(clip[level][5], abs=0.051)
    assert "above the input in PSNR and SSIM in every bin" not in text
