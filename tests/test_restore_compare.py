"""`restore --compare` and the one naming rule of restored outputs (docs/cli.md): NAME_restored.png / .mp4 and
NAME_compare.png / .mp4, NAME being the image's or video's stem or the clip folder's name. The panels of a compare
picture are found by searching it for the input and restored files read back independently."""

import numpy as np
import pytest
from PIL import Image
from skimage import data

from d2turb.cli import main


def _frames(n=6, size=64):
    """n frames of a natural image, each shifted by a pixel or two (a clip with some 'tilt')."""
    base = data.astronaut()[::4, ::4][:size, :size]
    return [np.roll(base, (i % 3 - 1, (i * 2) % 3 - 1), axis=(0, 1)) for i in range(n)]


def _find(picture: np.ndarray, panel: np.ndarray, x_from: int = 0) -> tuple[int, int] | None:
    """(y, x) where ``panel`` sits exactly in ``picture`` (search over every offset), None if nowhere."""
    h, w = panel.shape[:2]
    for y in range(picture.shape[0] - h + 1):
        for x in range(x_from, picture.shape[1] - w + 1):
            if picture[y, x, 0] == panel[0, 0, 0] and np.array_equal(picture[y : y + h, x : x + w], panel):
                return y, x
    return None


def _check_compare(picture: np.ndarray, before: np.ndarray, after: np.ndarray) -> None:
    """before on the left, after on its right at the same height, each with dark label text above it."""
    left = _find(picture, before)
    assert left is not None and left[1] == 0
    right = _find(picture, after, x_from=before.shape[1] + 1)
    assert right is not None and right[0] == left[0]
    y = left[0]
    assert y >= 12 and picture.shape[0] == y + before.shape[0]  # a label band on top, nothing below
    for x0 in (0, right[1]):
        band = picture[:y, x0 : x0 + before.shape[1]]
        assert (band.min(axis=2) < 100).sum() > 20, "no label above a panel"


def test_image_compare_is_input_beside_restored(tmp_path):
    Image.fromarray(_frames(1)[0]).save(tmp_path / "scene.png")
    out = tmp_path / "o"
    assert main(["restore", str(tmp_path / "scene.png"), "--compare", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["scene_compare.png", "scene_restored.png"]
    restored = np.asarray(Image.open(out / "scene_restored.png"))
    assert not np.array_equal(restored, _frames(1)[0])  # the shipped model changed it: the panels are told apart
    _check_compare(np.asarray(Image.open(out / "scene_compare.png")), _frames(1)[0], restored)


def test_folder_compare_one_per_image(tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    frames = _frames(2)
    for name, frame in zip("ab", frames):
        Image.fromarray(frame).save(src / f"{name}.png")
    out = tmp_path / "o"
    assert main(["restore", str(src), "--weights", "input", "--compare", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == sorted(
        f"{n}_{k}.png" for n in "ab" for k in ("compare", "restored")
    )
    for name, frame in zip("ab", frames):
        _check_compare(np.asarray(Image.open(out / f"{name}_compare.png")), frame, frame)


def test_clip_compare_png_and_side_by_side_mp4(tmp_path):
    """A folder clip: FOLDER_restored.mp4, FOLDER_compare.mp4 (one frame per input frame, input | restored) and
    FOLDER_compare.png of the middle frame (input frame 3 beside 3_restored.png)."""
    src = tmp_path / "street"
    src.mkdir()
    frames = _frames(6)
    for i, frame in enumerate(frames):
        Image.fromarray(frame).save(src / f"{i}.png")
    out = tmp_path / "o"
    assert main(["restore", str(src), "--temporal", "4", "--compare", "--dr0", "2", "--out", str(out)]) == 0
    names = sorted(p.name for p in out.iterdir())
    av = _av()
    videos = ["street_compare.mp4", "street_restored.mp4"] if av else []
    assert names == sorted([f"{i}_restored.png" for i in range(6)] + ["street_compare.png", "restore.json", *videos])
    restored = np.asarray(Image.open(out / "3_restored.png"))
    _check_compare(np.asarray(Image.open(out / "street_compare.png")), frames[3], restored)
    if av:
        picture = np.asarray(Image.open(out / "street_compare.png"))
        with av.open(str(out / "street_compare.mp4")) as c:
            decoded = [f.to_ndarray(format="rgb24") for f in c.decode(c.streams.video[0])]
        assert len(decoded) == 6
        h, w = picture.shape[:2]
        assert decoded[3].shape[:2] == (h + h % 2, w + w % 2)  # yuv420p pads odd sizes by one edge row/column
        assert (
            np.abs(decoded[3][:h, :w].astype(float) - picture).mean() < 10
        )  # the same picture, lossy codec (small, sharp)


def test_video_outputs_follow_the_rule(tmp_path):
    """A video restored as a clip and frame by frame: NAME_restored.mp4 and NAME_compare.mp4/.png, frames
    NAME_NNNNNN_restored.png (the video's own name is never reused for an output)."""
    av = _av()
    if not av:
        pytest.skip("video extra (PyAV) not installed")
    from d2turb.video import Mp4Writer

    with Mp4Writer(tmp_path / "take.mp4", fps=10) as w:
        for frame in _frames(5):
            w.write(frame)
    for extra, out in (
        (["--temporal", "3", "--dr0", "2"], tmp_path / "clip"),
        (["--weights", "input"], tmp_path / "f"),
    ):
        assert main(["restore", str(tmp_path / "take.mp4"), *extra, "--compare", "--out", str(out)]) == 0
        names = sorted(p.name for p in out.iterdir())
        expected = [f"take_{i:06d}_restored.png" for i in range(5)]
        record = ["restore.json"] if "--temporal" in extra else []  # a clip's deblur record
        assert names == sorted(expected + ["take_compare.mp4", "take_compare.png", "take_restored.mp4"] + record)


def _av():
    try:
        import av
    except ImportError:
        return None
    return av
