"""The formats turbulence is filmed in (issue 52 item 3): 16-bit in, 16-bit out; grey stays grey; SER videos and FITS
images and cubes read. Every file is made here: SER by its published layout (written with struct, not by the reader),
PNG/TIFF by imagecodecs, FITS by astropy."""

from __future__ import annotations

import os
import struct
import subprocess
import sys
from pathlib import Path

import imagecodecs
import numpy as np
import pytest

from d2turb.errors import D2TurbError
from d2turb.io.formats import PixelFormat, image_format, to_restorer, to_stored
from d2turb.io.read import read_stored
from d2turb.io.ser import iter_ser, read_ser_header

SRC = Path(__file__).resolve().parents[1] / "src"


def _scene(h=40, w=48, seed=0) -> np.ndarray:
    """A smooth scene in [0, 1] (H, W)."""
    y, x = np.mgrid[0:h, 0:w] / 7.0
    rng = np.random.default_rng(seed)
    return (0.5 + 0.3 * np.sin(x + rng.uniform(0, 3)) * np.cos(y) + 0.05 * rng.standard_normal((h, w))).clip(0, 1)


def _run(*argv, cwd=None) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(SRC), "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-m", "d2turb", *map(str, argv)], env=env, capture_output=True, text=True, timeout=300, cwd=cwd
    )


# ---- 16 bits and grey in images ----------------------------------------------------------------------------------
@pytest.mark.parametrize("suffix", [".png", ".tif"])
@pytest.mark.parametrize("channels", [1, 3])
def test_16_bit_images_are_read_with_their_16_bits_and_channels(tmp_path, suffix, channels):
    rng = np.random.default_rng(1)
    values = rng.integers(0, 65536, (9, 11, channels) if channels == 3 else (9, 11), dtype=np.uint16)
    path = tmp_path / f"img{suffix}"
    path.write_bytes(imagecodecs.png_encode(values) if suffix == ".png" else imagecodecs.tiff_encode(values))
    got = read_stored(path)
    assert got.dtype == np.uint16 and np.array_equal(got, values)  # Pillow alone gave 8 bits for RGB
    assert image_format(path) == PixelFormat(channels, 16)


def test_8_bit_grey_stays_one_channel(tmp_path):
    values = (np.arange(12 * 10) % 256).astype(np.uint8).reshape(12, 10)
    path = tmp_path / "g.png"
    path.write_bytes(imagecodecs.png_encode(values))
    assert read_stored(path).shape == (12, 10) and image_format(path) == PixelFormat(1, 8)


def test_every_16_bit_value_survives_the_restorers_float_and_back():
    values = np.arange(65536, dtype=np.uint16).reshape(256, 256)
    fmt = PixelFormat(1, 16)
    frame = to_restorer(values, fmt)  # (H,W,1) float32 in [0,1]
    assert frame.shape == (256, 256, 1) and frame.dtype == np.float32
    assert np.array_equal(to_stored(frame, fmt), values)


# ---- SER ---------------------------------------------------------------------------------------------------------
def _ser(path: Path, frames: np.ndarray, color_id: int, depth: int, flag: int, order="<", stamps=None) -> None:
    """A SER file by the format description v3: 178-byte header (little-endian fields), raw frames, timestamps."""
    n, h, w = frames.shape[:3]
    header = b"LUCAM-RECORDER" + struct.pack("<7i", 0, color_id, flag, w, h, depth, n)
    header += b"observer".ljust(40, b"\0") + b"camera".ljust(40, b"\0") + b"scope".ljust(40, b"\0")
    header += struct.pack("<2q", 0, 0)
    assert len(header) == 178
    dtype = np.uint8 if depth <= 8 else np.dtype(f"{order}u2")
    body = frames.astype(dtype).tobytes()
    tail = b"" if stamps is None else struct.pack(f"<{n}q", *stamps)
    path.write_bytes(header + body + tail)


@pytest.mark.parametrize(("flag", "order"), [(0, "<"), (1, ">")])
def test_ser_16_bit_mono_frames_equal_what_was_written(tmp_path, flag, order):
    rng = np.random.default_rng(2)
    frames = rng.integers(0, 65536, (3, 6, 8), dtype=np.uint16)
    path = tmp_path / "c.ser"
    _ser(path, frames, 0, 16, flag, order, stamps=[0, 400_000, 800_000])  # 25 frames/s in 100-ns ticks
    header = read_ser_header(path)
    assert (header.frames, header.width, header.height, header.channels) == (3, 8, 6, 1)
    assert header.fps == pytest.approx(25.0)
    got = list(iter_ser(path))
    assert all(g.dtype == np.uint16 and g.shape == (6, 8) for g in got)
    assert np.array_equal(np.stack(got), frames)


def test_ser_12_bit_samples_settle_the_byte_order_and_fill_16_bits(tmp_path):
    frames = np.random.default_rng(3).integers(0, 4096, (2, 5, 7), dtype=np.uint16)
    path = tmp_path / "c12.ser"
    _ser(path, frames, 0, 12, flag=0, order=">")  # the flag says little-endian, the samples are big-endian
    assert np.array_equal(np.stack(list(iter_ser(path))), frames << 4)


def test_ser_8_bit_rgb_bgr_and_bayer(tmp_path):
    rng = np.random.default_rng(4)
    rgb = rng.integers(0, 256, (2, 6, 8, 3), dtype=np.uint8)
    _ser(tmp_path / "rgb.ser", rgb, 100, 8, 0)
    _ser(tmp_path / "bgr.ser", rgb[..., ::-1], 101, 8, 0)
    for name in ("rgb.ser", "bgr.ser"):
        assert np.array_equal(np.stack(list(iter_ser(tmp_path / name))), rgb)
    # a flat colour through an RGGB mosaic demosaics to that colour (away from the border)
    colour = (200, 100, 50)
    mosaic = np.empty((1, 8, 10), np.uint8)
    mosaic[:, 0::2, 0::2], mosaic[:, 0::2, 1::2], mosaic[:, 1::2, 0::2], mosaic[:, 1::2, 1::2] = (
        colour[0],
        colour[1],
        colour[1],
        colour[2],
    )
    _ser(tmp_path / "bayer.ser", mosaic, 8, 8, 0)
    (frame,) = iter_ser(tmp_path / "bayer.ser")
    assert frame.shape == (8, 10, 3)
    assert np.array_equal(frame[2:-2, 2:-2], np.broadcast_to(np.array(colour, np.uint8), (4, 6, 3)))


def test_not_a_ser_file_is_one_line(tmp_path):
    (tmp_path / "x.ser").write_bytes(b"NOT-A-SER" + bytes(200))
    with pytest.raises(D2TurbError, match="not a SER file"):
        read_ser_header(tmp_path / "x.ser")


# ---- FITS --------------------------------------------------------------------------------------------------------
def test_fits_cube_of_16_bit_frames_round_trips(tmp_path):
    fits = pytest.importorskip("astropy.io.fits")
    from d2turb.io.fits import iter_fits, read_fits_image

    cube = np.random.default_rng(5).integers(0, 65536, (4, 6, 9), dtype=np.uint16)
    fits.PrimaryHDU(cube).writeto(tmp_path / "cube.fits")  # stored as int16 with BZERO 32768
    got = list(iter_fits(tmp_path / "cube.fits"))
    assert len(got) == 4 and all(g.dtype == np.uint16 for g in got)
    assert np.array_equal(np.stack(got), cube[:, ::-1])  # FITS's first row is the bottom one
    fits.PrimaryHDU(cube[0].astype(np.float32) / 65535).writeto(tmp_path / "one.fits")
    one = read_fits_image(tmp_path / "one.fits")
    assert one.dtype == np.float32 and np.allclose(one, cube[0, ::-1] / 65535, atol=1e-7)


def test_fits_without_astropy_is_one_error_line(tmp_path, monkeypatch):
    from d2turb.io.fits import iter_fits

    (tmp_path / "a.fits").write_bytes(b"SIMPLE  =                    T" + b" " * 2850)
    monkeypatch.setitem(sys.modules, "astropy.io", None)  # import fails as where astropy is not installed
    with pytest.raises(D2TurbError, match=r"needs astropy; install the fits extra"):
        next(iter_fits(tmp_path / "a.fits"))


# ---- end to end --------------------------------------------------------------------------------------------------
def test_16_bit_rgb_clip_gives_16_bit_restored_frames(tmp_path):
    """A still 16-bit clip, fused without a deblur, gives back its frame (the oracle) in 16 bits: the restored
    values are those of the input, not of an 8-bit copy."""
    scene = np.stack([_scene(seed=0), _scene(seed=1), _scene(seed=2)], -1)
    values = np.rint(scene * 65535).astype(np.uint16)
    clip = tmp_path / "clip16"
    clip.mkdir()
    for i in range(6):
        (clip / f"{i:03d}.tif").write_bytes(imagecodecs.tiff_encode(values))
    res = _run("restore", clip, "--temporal", 4, "--out", tmp_path / "out", "--deblur", "none", "--fusion", "mean")
    assert res.returncode == 0, res.stderr
    out = imagecodecs.imread(tmp_path / "out" / "003_restored.png")
    assert out.dtype == np.uint16 and out.shape == values.shape
    # an 8-bit copy would be off by 64 on average (uniform rounding to multiples of 257)
    assert np.abs(out.astype(int) - values).mean() < 16
    assert len(np.unique(out % 257)) > 200  # not 8-bit values scaled


def test_16_bit_grey_image_restored_by_a_model_stays_16_bit_grey(tmp_path):
    """restore IMAGE with the identity baseline (--weights input) writes the input back: grey, 16 bits."""
    values = np.rint(_scene() * 65535).astype(np.uint16)
    (tmp_path / "g16.png").write_bytes(imagecodecs.png_encode(values))
    res = _run("restore", tmp_path / "g16.png", "--weights", "input", "--out", tmp_path / "out")
    assert res.returncode == 0, res.stderr
    out = imagecodecs.imread(tmp_path / "out" / "g16_restored.png")
    assert out.dtype == np.uint16 and np.array_equal(out, values)


def test_grey_clip_stays_grey_and_equals_the_grey_of_its_rgb_restoration(tmp_path):
    """A grey clip comes out grey (H,W), and as its RGB copy (grey in every channel) comes out: the restoration
    does the same to each channel (the oracle: the same clip as RGB)."""
    rng = np.random.default_rng(6)
    grey, rgb = tmp_path / "grey", tmp_path / "rgb"
    grey.mkdir(), rgb.mkdir()
    base = _scene(48, 56)
    for i in range(8):
        shifted = np.roll(base, (int(rng.integers(-1, 2)), int(rng.integers(-1, 2))), (0, 1))
        frame = np.rint(shifted * 255).astype(np.uint8)
        (grey / f"{i:03d}.png").write_bytes(imagecodecs.png_encode(frame))
        (rgb / f"{i:03d}.png").write_bytes(imagecodecs.png_encode(np.repeat(frame[..., None], 3, 2)))
    for clip in (grey, rgb):
        res = _run("restore", clip, "--temporal", 4, "--out", tmp_path / f"out_{clip.name}", "--dr0", 2)
        assert res.returncode == 0, res.stderr
    for i in range(8):
        g = imagecodecs.imread(tmp_path / "out_grey" / f"{i:03d}_restored.png")
        c = imagecodecs.imread(tmp_path / "out_rgb" / f"{i:03d}_restored.png")
        assert g.shape == (48, 56) and g.dtype == np.uint8
        assert np.abs(g.astype(int) - c.astype(int).mean(axis=2)).max() <= 1


def test_ser_rgb_clip_restores_into_named_frames_and_an_mp4(tmp_path):
    pytest.importorskip("av")
    scene = np.rint(np.stack([_scene(seed=s) for s in (0, 1, 2)], -1) * 255).astype(np.uint8)
    _ser(tmp_path / "moon.ser", np.stack([scene] * 5), 100, 8, 0)
    res = _run("restore", tmp_path / "moon.ser", "--temporal", 3, "--out", tmp_path / "out", "--deblur", "none")
    assert res.returncode == 0, res.stderr
    out = tmp_path / "out"
    assert sorted(p.name for p in out.glob("*_restored.png")) == [f"moon_{i:06d}_restored.png" for i in range(5)]
    assert (out / "moon_restored.mp4").stat().st_size > 0
    assert np.abs(imagecodecs.imread(out / "moon_000002_restored.png").astype(int) - scene).max() <= 1


def test_fits_cube_clip_restores_into_16_bit_grey_frames(tmp_path):
    fits = pytest.importorskip("astropy.io.fits")
    values = np.rint(_scene() * 65535).astype(np.uint16)
    fits.PrimaryHDU(np.stack([values[::-1]] * 5)).writeto(tmp_path / "sun.fits")
    res = _run("restore", tmp_path / "sun.fits", "--temporal", 3, "--out", tmp_path / "out", "--deblur", "none")
    assert res.returncode == 0, res.stderr
    out = imagecodecs.imread(tmp_path / "out" / "sun_000002_restored.png")
    assert out.dtype == np.uint16 and out.shape == values.shape
    assert np.abs(out.astype(int) - values).mean() < 16 and len(np.unique(out % 257)) > 200  # see the RGB clip


@pytest.mark.parametrize(("pix_fmt", "dtype"), [("gray16le", np.uint16), ("gray", np.uint8)])
def test_grey_and_16_bit_video_frames_keep_their_samples(tmp_path, pix_fmt, dtype):
    """A lossless grey video (FFV1, written by PyAV) decodes to (H,W) frames of its own depth, every sample kept."""
    av = pytest.importorskip("av")
    from d2turb.video import VideoSource

    top = np.iinfo(dtype).max
    frames = [np.rint(_scene(seed=s) * top).astype(dtype) for s in range(3)]
    with av.open(str(tmp_path / "g.mkv"), "w") as container:
        stream = container.add_stream("ffv1", rate=10)
        stream.width, stream.height, stream.pix_fmt = 48, 40, pix_fmt
        for i, frame in enumerate(frames):
            video = av.VideoFrame.from_ndarray(frame, pix_fmt)
            video.pts = i
            for packet in stream.encode(video):
                container.mux(packet)
        for packet in stream.encode(None):
            container.mux(packet)
    source = VideoSource(tmp_path / "g.mkv")
    assert (source.channels, source.bits) == (1, 16 if dtype == np.uint16 else 8)
    got = list(source)
    assert all(g.dtype == dtype and g.shape == (40, 48) for g in got)
    assert all(np.array_equal(g, f) for g, f in zip(got, frames))
