"""Sharpest-coefficient fusion (d2turb.clip.fusion, ``--fusion sharpest``) against known truths: frames of one
image blurred by different known kernels, identical frames, an outlier frame (a square that is there in one frame
only), the streamed choice against the direct one."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage
from skimage import data as skdata

from d2turb.clip import ClipRestorer
from d2turb.clip.sharpest import (
    SharpestFusion,
    collapse_pyramid,
    laplacian_pyramid,
    robust_reference,
    sharp_coefficients,
    sharpest_fusion,
)
from d2turb.errors import D2TurbError


def _scene(size=128) -> np.ndarray:
    img = skdata.astronaut()[100 : 100 + size, 150 : 150 + size].astype(np.float32) / 255.0
    return np.ascontiguousarray(img)


def _blur(img: np.ndarray, sigma: float) -> np.ndarray:
    return np.stack([ndimage.gaussian_filter(img[..., c], sigma) for c in range(3)], -1).astype(np.float32)


INNER = (slice(12, -12), slice(12, -12))


def _mse(x, truth):
    return float(((x - truth)[INNER] ** 2).mean())


def test_pyramid_collapses_back_exactly():
    img = np.random.default_rng(0).random((53, 70, 3)).astype(np.float32)
    for levels in (1, 3, 4):
        np.testing.assert_allclose(collapse_pyramid(laplacian_pyramid(img, levels)), img, atol=1e-5)


def test_an_8_bit_frames_fixed_point_pyramid_collapses_back_within_a_fraction_of_a_grey_level():
    """The sharpest fusion holds its pyramids in int16 of 1/FIXED_ONE (1/64 of a grey level): an 8-bit frame's comes
    back within 1/32 of a grey level (OpenCV rounds each level once), a float frame's within the fixed point's step."""
    from d2turb.clip.sharpest import FIXED_ONE, to_fixed

    rng = np.random.default_rng(1)
    u8 = rng.integers(0, 256, (53, 70, 3), dtype=np.uint8)
    assert np.array_equal(to_fixed(u8), u8.astype(np.int32) * FIXED_ONE // 255)  # v/255 exactly
    for levels in (1, 3, 4):
        pyramid = [p.astype(np.float32) for p in laplacian_pyramid(to_fixed(u8), levels)]
        back = collapse_pyramid(pyramid) / FIXED_ONE
        assert np.abs(back - u8 / 255.0).max() * 255 < 1 / 32
    img = rng.random((40, 30, 3)).astype(np.float32)
    assert np.abs(to_fixed(img) / FIXED_ONE - img).max() <= 0.5 / FIXED_ONE + 1e-7
    img[0, 0] = [np.nan, np.inf, -np.inf]  # a defined value for every float, ±inf clipped to ±2
    assert to_fixed(img)[0, 0].tolist() == [0, 2 * FIXED_ONE, -2 * FIXED_ONE]


def test_frames_blurred_by_known_kernels_fuse_closer_to_the_sharp_image_than_their_mean():
    """Six frames of one image, each blurred by a known Gaussian (σ 0.5–2.5 px, one per frame), and four frames each
    sharp in one quadrant only (σ 0.3 there, 2 px elsewhere: anisoplanatic blur): the fusion is measurably closer to
    the sharp image than the frames' mean."""
    img = _scene(128)
    stack = [_blur(img, s) for s in (0.5, 1.5, 2.5, 2.0, 1.0, 2.5)]
    mean, fused = _mse(np.mean(stack, 0), img), _mse(sharpest_fusion(stack), img)
    assert fused < 0.6 * mean, (fused, mean)

    sharp, soft = _blur(img, 0.3), _blur(img, 2.0)
    quads = [
        (slice(0, 64), slice(0, 64)),
        (slice(0, 64), slice(64, 128)),
        (slice(64, 128), slice(0, 64)),
        (slice(64, 128), slice(64, 128)),
    ]
    stack = []
    for q in quads:
        f = soft.copy()
        f[q] = sharp[q]
        stack.append(f)
    mean, fused = _mse(np.mean(stack, 0), img), _mse(sharpest_fusion(stack), img)
    # each quadrant mostly from the frame that holds it sharp (its finest details, above 3 × the window's mean
    # amplitude, count as outliers and stay the mean's)
    assert fused < 0.4 * mean, (fused, mean)


def test_identical_frames_fuse_to_themselves():
    img = _scene(96)
    np.testing.assert_allclose(sharpest_fusion([img] * 5), img, atol=2e-3)  # float16 coefficients


def test_an_outlier_frame_does_not_print_into_the_fusion():
    """Eight noisy frames of a static scene, a red square in one of them only: the fusion of the window shows the
    background there (within the noise), where the mean prints an eighth of the square; through the clip pipeline,
    the outputs of the other frames show no ghost."""
    rng = np.random.default_rng(4)
    img = _scene(128)
    frames = [np.clip(img + 0.01 * rng.standard_normal(img.shape), 0, 1).astype(np.float32) for _ in range(8)]
    frames[3][50:70, 40:60] = [1.0, 0.0, 0.0]
    square = (slice(50, 70), slice(40, 60))
    fused = sharpest_fusion(frames)
    ghost = float(np.abs(fused - img)[square].mean())
    plain = float(np.abs(np.mean(frames, 0) - img)[square].mean())
    elsewhere = float(np.abs(fused - img)[50:70, 80:100].mean())  # the fusion's own error where no square ever was
    assert ghost < 1.5 * elsewhere and ghost < 0.2 * plain, (ghost, elsewhere, plain)

    tensors = [torch.from_numpy(f).permute(2, 0, 1).contiguous() for f in frames]
    truth = torch.from_numpy(img).permute(2, 0, 1)
    for o in ClipRestorer(temporal=8, fusion="sharpest").restore(tensors):
        err = float((o.fused - truth)[:, 50:70, 40:60].abs().mean())
        if o.index == 3:
            assert float(o.fused[0, 52:68, 42:58].mean()) > 0.9  # the frame's own object stays (its fallback)
        else:
            assert err < 0.02, (o.index, err)


def test_a_moving_object_is_restored_from_its_frame_as_with_the_mean():
    """A dark square moving 8 px a frame over a static scene whose frames are blurred by different known kernels (so
    the sharpest fusion is much sharper than any frame): every output shows the square as its own frame does (the
    frame is the truth of a moving object), within a few grey levels on average, as the mean fusion's output does.
    The moving-object decision against the sharpest fusion itself let half the square ghost (8.4 grey levels)."""
    rng = np.random.default_rng(8)
    img = _scene(128)
    frames, boxes = [], []
    for t, sigma in enumerate(rng.uniform(0.5, 2.5, 12)):
        f = _blur(img, sigma) + 0.01 * rng.standard_normal(img.shape).astype(np.float32)
        box = (slice(50, 74), slice(10 + 8 * t, 34 + 8 * t))
        f[box] = f[box] * 0.4 + np.array([0.05, 0.1, 0.3], np.float32)
        frames.append(np.clip(f, 0, 1))
        boxes.append(box)
    tensors = [torch.from_numpy(f).permute(2, 0, 1) for f in frames]
    errors = {}
    for fusion in ("mean", "sharpest"):
        outs = ClipRestorer(temporal=8, fusion=fusion).restore(tensors)
        errors[fusion] = np.mean(
            [np.abs(o.fused.permute(1, 2, 0).numpy() - frames[o.index])[boxes[o.index]].mean() * 255 for o in outs]
        )
    assert errors["sharpest"] < 4.0 and errors["sharpest"] < 1.5 * errors["mean"], errors


def test_the_streamed_choice_equals_the_direct_one():
    """Windows sliding over a stream: the incremental choice (a leaving frame's pixels re-chosen among the others)
    gives the fusion computed from scratch for each window (the same choice; running sums to float32 rounding)."""
    rng = np.random.default_rng(5)
    img = _scene(64)
    frames = [_blur(img, s) + 0.01 * rng.standard_normal(img.shape).astype(np.float32) for s in rng.uniform(0.3, 2, 14)]
    ref = robust_reference(frames)
    coeffs = {i: sharp_coefficients(f, ref) for i, f in enumerate(frames)}
    streamed = SharpestFusion()
    for lo in [0, 0, 1, 2, 3, 4, 5, 6, 6]:
        window = {j: coeffs[j] for j in range(lo, lo + 8)}
        mean = np.mean(frames[lo : lo + 8], axis=0, dtype=np.float32)
        np.testing.assert_allclose(streamed.fuse(window, mean), SharpestFusion().fuse(window, mean), atol=1e-5)


def test_sharpest_errors_are_one_line():
    with pytest.raises(D2TurbError, match="at least one frame"):
        sharpest_fusion([])
    with pytest.raises(D2TurbError, match="at least one frame"):
        SharpestFusion().fuse({}, np.zeros((4, 4, 3), np.float32))


def test_the_physics_deblur_after_the_sharpest_fusion_models_a_weaker_blur():
    from d2turb.clip import SHARPEST_DR0_SCALE, deblur_dr0

    assert deblur_dr0(3.0, "mean") == 3.0 and deblur_dr0(3.0, "fba") == 3.0
    assert 0 < SHARPEST_DR0_SCALE < 1 and deblur_dr0(3.0, "sharpest") == pytest.approx(3.0 * SHARPEST_DR0_SCALE)


def test_memory_stays_bounded_on_a_long_stream():
    """A stream of 80 frames, window 6: the fusion holds the pyramids of one window at most, and the frames' images
    stay bounded by the window as with the mean (about 3.5 windows' worth)."""
    rng = np.random.default_rng(6)
    base = _scene(32)
    restorer = ClipRestorer(temporal=6, fusion="sharpest")
    frames = (np.clip(base + 0.01 * rng.standard_normal(base.shape), 0, 1).astype(np.float32) for _ in range(80))
    held, count = [], 0
    for _ in restorer.restore(frames):
        held.append((len(restorer.state.fusion.choice.amps), restorer.state.buffered))
        count += 1
    assert count == 80
    assert max(h[0] for h in held) <= 6 and max(h[1] for h in held) <= 4 * 6, held


def test_the_pyramids_held_never_exceed_one_window_even_at_the_clip_end(monkeypatch):
    """Each registered frame's pyramid lives while a window holds it: at every output, the pyramids alive are at
    most one window's (+1, the frame just registered), also once the clip's end is read, when every later window is
    ready at once (the registration used to run ahead then: 1.5 windows at 1080p, 0.3 GB)."""
    import weakref

    import d2turb.clip.fusion as fusion

    made = []  # weak references: a pyramid is alive while the restorer holds it
    make = fusion.sharp_coefficients

    def tracked(*args, **kwargs):
        out = make(*args, **kwargs)
        made.append(weakref.ref(out))
        return out

    monkeypatch.setattr(fusion, "sharp_coefficients", tracked)
    rng = np.random.default_rng(7)
    base = _scene(32)
    frames = (np.clip(base + 0.01 * rng.standard_normal(base.shape), 0, 1).astype(np.float32) for _ in range(40))
    counts = [sum(r() is not None for r in made) for _ in ClipRestorer(temporal=8, fusion="sharpest").restore(frames)]
    assert len(counts) == 40 and max(counts) <= 8 + 1, counts


def test_restore_without_a_deblur_fuses_the_sharpest_unless_told(tmp_path):
    """``restore --temporal N --deblur none`` (no ``--fusion``): the sharpest fusion, measurably closer to the sharp
    scene than ``--fusion mean`` on frames of one scene blurred by different known kernels; restore.json names the
    fusion used; before a deblur the default stays the mean (its blur is the one the Wiener filter models)."""
    import json

    from d2turb.cli import main
    from d2turb.io import read_image, write_image
    from d2turb.restore.clip_build import ClipOptions

    img = _scene(96)
    clip = tmp_path / "clip"
    clip.mkdir()
    for i, s in enumerate((0.5, 1.5, 2.5, 2.0, 1.0, 2.5)):
        write_image(clip / f"{i}.png", torch.from_numpy(_blur(img, s)).permute(2, 0, 1))
    errors = {}
    for name, extra in (("default", []), ("mean", ["--fusion", "mean"])):
        out = tmp_path / name
        assert main(["restore", str(clip), "--temporal", "6", "--deblur", "none", "--out", str(out), *extra]) == 0
        assert json.loads((out / "restore.json").read_text())["fusion"] == ("sharpest" if name == "default" else name)
        errors[name] = _mse(read_image(out / "2_restored.png").permute(1, 2, 0).numpy(), img)
    assert errors["default"] < 0.6 * errors["mean"], errors
    assert ClipOptions(deblur="auto").fusion_used == "mean" and ClipOptions(deblur="physics").fusion_used == "mean"
    assert ClipOptions(deblur="none", fusion="fba").fusion_used == "fba"


def test_the_fusion_thread_gives_the_serial_outputs_and_stops_with_the_stream():
    """The sharpest fusion runs in a thread of its own while the next frames register: its outputs are those of the
    same stream run serially (to the bit), and a stream closed early leaves no fusion thread behind."""
    import threading

    rng = np.random.default_rng(8)
    base = _scene(48)
    frames = [
        np.clip(_blur(base, s) + 0.01 * rng.standard_normal(base.shape), 0, 1).astype(np.float32)
        for s in rng.uniform(0.3, 2, 20)
    ]
    threaded = list(ClipRestorer(temporal=6, fusion="sharpest").restore(iter(frames)))
    serial = list(ClipRestorer(temporal=6, fusion="sharpest", threaded=False).restore(iter(frames)))
    assert [o.index for o in threaded] == list(range(20)) == [o.index for o in serial]
    for a, b in zip(threaded, serial):
        assert torch.equal(a.fused, b.fused) and torch.equal(a.fallback, b.fallback)
    stream = ClipRestorer(temporal=6, fusion="sharpest").restore(iter(frames))
    next(stream)
    stream.close()
    assert not [t for t in threading.enumerate() if t.name.startswith("d2turb-fuse")]
