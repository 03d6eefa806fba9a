"""`d2turb restore` end to end: outputs, odd inputs (16-bit grey, alpha, EXIF), videos, errors."""

import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from hostile_input import CHILD_ENV, bad_files, error_lines, rgb, run_cli, temp_files
from PIL import Image

from d2turb.cli import main
from d2turb.io import read_image


def _rgb(h=24, w=40, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def test_restore_identity_writes_all_outputs(tmp_path, capsys):
    src = tmp_path / "in"
    src.mkdir()
    Image.fromarray(_rgb()).save(src / "a.png")
    Image.fromarray(_rgb(seed=1)).convert("RGBA").save(src / "b.png")
    grey16 = (np.random.default_rng(2).integers(0, 65536, (30, 20))).astype(np.uint16)
    Image.fromarray(grey16).save(src / "c.png")
    out = tmp_path / "out"
    rc = main(["restore", str(src), "--weights", "input", "--out", str(out), "--save-flow", "--save-intermediate"])
    assert rc == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(f"{s}_{k}" for s in "abc" for k in ("restored.png", "bwd_flow_px.npy", "deblurred.png"))
    # identity restorer: the output is the input, up to 8-bit quantisation of the 16-bit grey
    np.testing.assert_array_equal(np.asarray(Image.open(out / "a_restored.png")), _rgb())
    c = read_image(out / "c_restored.png")
    assert c.shape == (3, 30, 20)
    assert (c[0] - torch.from_numpy(grey16 / 65535.0).float()).abs().max() <= 0.5 / 255 + 1e-6
    flow = np.load(out / "b_bwd_flow_px.npy")
    assert flow.dtype == np.float32 and flow.shape == (2, 24, 40) and not flow.any()
    assert "restored 3 image(s)" in capsys.readouterr().out


def test_exif_orientation_is_respected(tmp_path):
    img = Image.fromarray(_rgb(20, 40))
    exif = img.getexif()
    exif[0x0112] = 6  # displayed rotated 90° clockwise → 40 rows x 20 columns
    img.save(tmp_path / "r.jpg", exif=exif, quality=95)
    assert main(["restore", str(tmp_path / "r.jpg"), "--weights", "input", "--out", str(tmp_path / "o")]) == 0
    assert Image.open(tmp_path / "o" / "r_restored.png").size == (20, 40)


def test_animated_gif_video_to_frames(tmp_path):
    frames = [Image.fromarray(_rgb(16, 16, seed=i)) for i in range(3)]
    frames[0].save(tmp_path / "clip.gif", save_all=True, append_images=frames[1:], duration=50, loop=0)
    pytest.importorskip("imageio")
    assert main(["restore", str(tmp_path / "clip.gif"), "--weights", "input", "--out", str(tmp_path / "o")]) == 0
    frames = sorted(p.name for p in (tmp_path / "o").glob("*.png"))
    assert frames == [f"clip_{i:06d}_restored.png" for i in range(3)]
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == sorted(
        [*(["clip_restored.mp4"] if _has_av() else []), *frames]
    )


def _has_av() -> bool:
    try:
        import av  # noqa: F401
    except ImportError:
        return False
    return True


def test_unreadable_video_names_the_extra(tmp_path, capsys):
    (tmp_path / "v.mp4").write_bytes(b"\x00" * 64)
    assert main(["restore", str(tmp_path / "v.mp4"), "--weights", "input", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]  # earlier lines: the progress bar
    assert err.startswith("error: ") and "d2turb[video]" in err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--weights", "nonexistent-name"], "not found; looked in:"),
        (["--weights", "input", "--tile", "64", "--overlap", "60"], "overlap must be between"),
    ],
)
def test_errors_are_one_line(tmp_path, capsys, argv, message):
    Image.fromarray(_rgb()).save(tmp_path / "a.png")
    rc = main(["restore", str(tmp_path / "a.png"), "--out", str(tmp_path / "o"), *argv])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.startswith("error: ") and message in err and "\n" not in err


def test_duplicate_output_names_rejected(tmp_path, capsys):
    for d in ("x", "y"):
        (tmp_path / d).mkdir()
        Image.fromarray(_rgb()).save(tmp_path / d / "same.png")
    rc = main(["restore", str(tmp_path / "x"), str(tmp_path / "y"), "--weights", "input", "--out", str(tmp_path / "o")])
    assert rc == 2 and "same" in capsys.readouterr().err


def test_mp4_video_to_frames(tmp_path):
    pytest.importorskip("av")
    iio = pytest.importorskip("imageio.v3")
    frames = np.stack([np.full((32, 48, 3), 40 * i + 20, dtype=np.uint8) for i in range(4)])
    iio.imwrite(tmp_path / "clip.mp4", frames, plugin="pyav", codec="libx264", fps=10)
    assert main(["restore", str(tmp_path / "clip.mp4"), "--weights", "input", "--out", str(tmp_path / "o")]) == 0
    out = sorted((tmp_path / "o").glob("*.png"))
    assert [p.name for p in out] == [f"clip_{i:06d}_restored.png" for i in range(4)]
    for i, path in enumerate(out):  # identity restorer: each frame's grey level survives the lossy codec
        assert np.abs(np.asarray(Image.open(path)).astype(float).mean() - (40 * i + 20)) < 3
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == sorted(["clip_restored.mp4", *(p.name for p in out)])


def test_mp4_in_mp4_out_with_the_input_frame_count_and_fps(tmp_path):
    """`restore clip.mp4 --weights input --out DIR` writes DIR/clip_restored.mp4 (video extra), read back here by PyAV
    directly (not through d2turb.video): the input's frame count, frame rate and size, and its frames."""
    av = pytest.importorskip("av")
    iio = pytest.importorskip("imageio.v3")
    levels = [30, 90, 150, 210, 120]
    frames = np.stack([np.full((32, 48, 3), v, dtype=np.uint8) for v in levels])
    iio.imwrite(tmp_path / "clip.mp4", frames, plugin="pyav", codec="libx264", fps=12)
    assert main(["restore", str(tmp_path / "clip.mp4"), "--weights", "input", "--out", str(tmp_path / "o")]) == 0
    with av.open(str(tmp_path / "clip.mp4")) as src:
        rate_in = src.streams.video[0].average_rate
    with av.open(str(tmp_path / "o" / "clip_restored.mp4")) as out:
        stream = out.streams.video[0]
        decoded = [f.to_ndarray(format="rgb24") for f in out.decode(stream)]
        rate_out = stream.average_rate
    assert float(rate_in) == pytest.approx(12) and float(rate_out) == pytest.approx(float(rate_in))
    assert len(decoded) == len(levels) and decoded[0].shape == (32, 48, 3)
    for frame, level in zip(decoded, levels):  # identity restorer, two lossy encodes
        assert abs(frame.astype(float).mean() - level) < 4


@pytest.fixture
def tiny_weights(tmp_path_factory):
    """A tiny NAFNet whose (finite, checksummed) weights overflow to inf/NaN in its forward pass."""
    from _tiny_models import TINY_NAFNET

    from d2turb.models import create_model, save_pretrained

    torch.manual_seed(0)
    model = create_model("nafnet", **TINY_NAFNET)
    with torch.no_grad():
        model.backbone.intro.weight.fill_(1e30)
    path = tmp_path_factory.mktemp("weights") / "overflow.safetensors"
    save_pretrained(model, path)
    return path


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
    proc = subprocess.Popen(cmd, env=CHILD_ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None and not (killed.is_dir() and any(killed.iterdir())):
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    assert proc.wait() == -signal.SIGKILL, "the run finished before it could be killed"
    rc, _, err = run_cli(capsys, [*argv, str(killed)])
    assert rc == 1 and len(error_lines(err)) == len(bad), err
    assert not temp_files(killed)
    assert {p.name: p.read_bytes() for p in killed.iterdir()} == reference


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
