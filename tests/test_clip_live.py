"""The live preset (``restore --temporal N --preset fast``, :mod:`d2turb.clip.live`): oracles independent of the code
(a linear flow field, known rigid shifts and a known smooth tilt recovered, a static scene kept within what
interpolation alone changes, the per-channel Wiener filter on a grey frame), the stream's bookkeeping, and the
command line's presets."""

from __future__ import annotations

import subprocess
import sys

import cv2
import numpy as np
import pytest
import torch

from d2turb.clip import PhysicsDeblur
from d2turb.clip.deblur import tone_guard
from d2turb.clip.live import (
    LIVE_JITTER_PX,
    LIVE_LOSS_DB,
    LIVE_LOSS_PLAIN_DB,
    PRESETS,
    LiveRestorer,
    dis_preset,
    live_deblurred,
    upsampled_flow,
)
from d2turb.clip.live_state import upsampled_maps
from d2turb.errors import D2TurbError

SHIFT_TOLERANCE_PX = 0.1  # what a registration that works must reach on a textured scene (DIS: ~0.02 px)


def _scene(h: int = 96, w: int = 128, seed: int = 0) -> np.ndarray:
    """A smooth random texture (H,W,3) float32 in [0, 1]: DIS has gradients everywhere, nothing aliases."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.random((h, w, 3)).astype(np.float32), (0, 0), 2.0)
    img -= img.min()
    return img / img.max()


def _moved(scene: np.ndarray, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """scene(x + dx(x), y + dy(x)), bicubic, edges replicated."""
    h, w = scene.shape[:2]
    xx, yy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(scene, xx + dx, yy + dy, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)


def _interpolation_bound(scene: np.ndarray, shift_px: float) -> float:
    """The most a bilinear resampling at a shift of ``shift_px`` per axis changes a pixel: shift × the largest step
    between neighbours along x plus along y."""
    gx = np.abs(np.diff(scene, axis=1)).max()
    gy = np.abs(np.diff(scene, axis=0)).max()
    return float(shift_px * (gx + gy))


def test_upsampled_flow_reproduces_a_linear_field():
    """A linear displacement u(X) = A·X + b (full-size px) sampled at the small image's pixel centres, X = (x + ½)/s
    − ½, in small px (× s): bilinear upsampling gives u at every full-size pixel away from the border."""
    h, w, s = 64, 96, 0.5
    a = np.array([[0.01, -0.02], [0.03, 0.005]])
    b = np.array([0.7, -1.2])
    hs, ws = int(h * s), int(w * s)
    xs, ys = np.meshgrid((np.arange(ws) + 0.5) / s - 0.5, (np.arange(hs) + 0.5) / s - 0.5)
    small = np.stack([a[0, 0] * xs + a[0, 1] * ys + b[0], a[1, 0] * xs + a[1, 1] * ys + b[1]], -1) * s
    full = upsampled_flow(small.astype(np.float32), (h, w))
    xx, yy = np.meshgrid(np.arange(w), np.arange(h))
    want = np.stack([a[0, 0] * xx + a[0, 1] * yy + b[0], a[1, 0] * xx + a[1, 1] * yy + b[1]], -1)
    inner = (slice(2, -2), slice(2, -2))
    assert full.shape == (h, w, 2) and full.dtype == np.float32
    np.testing.assert_allclose(full[inner], want[inner], atol=1e-4)


@pytest.mark.parametrize("shape, small", [((72, 128), (36, 64)), ((101, 77), (50, 38)), ((60, 60), (15, 15))])
def test_upsampled_maps_are_the_grid_plus_the_upsampled_flow(shape, small):
    """The remap coordinates made in one pass equal the pixel grid plus the upsampled flow (float rounding apart)."""
    flow = cv2.GaussianBlur(np.random.default_rng(0).normal(0, 2, (*small, 2)).astype(np.float32), (0, 0), 3)
    want = upsampled_flow(flow, shape) + np.stack(np.meshgrid(np.arange(shape[1]), np.arange(shape[0])), -1)
    np.testing.assert_allclose(upsampled_maps(flow, shape), want, atol=1e-3)


def test_static_scene_kept_within_interpolation():
    """Twelve identical frames: the output is the scene within what a bilinear resampling at the registration's
    tolerance (0.1 px) can change, and the 8-bit rounding of the frames."""
    scene = _scene()
    frames = [(scene * 255 + 0.5).astype(np.uint8)] * 12
    outs = list(LiveRestorer(temporal=6).restore(frames))
    bound = _interpolation_bound(frames[0] / 255.0, SHIFT_TOLERANCE_PX) + 1 / 255
    for o in outs:
        got = o.restored.permute(1, 2, 0).numpy()
        assert np.abs(got - frames[0] / 255.0).max() <= bound


@pytest.mark.parametrize("threaded", [True, False])
def test_known_rigid_shifts_recovered(threaded):
    """Frames are the scene shifted by ±0.8 px in x and ∓0.5 px in y, alternating (every even window's mean shift is
    zero): each frame's flow is minus its shift, frame(x + flow) = scene(x), and the output is the scene within the
    interpolation bound of the registration's tolerance."""
    scene = _scene(seed=1)
    h, w = scene.shape[:2]
    shifts = [(0.8, -0.5) if i % 2 else (-0.8, 0.5) for i in range(20)]
    frames = [_moved(scene, np.full((h, w), dx, np.float32), np.full((h, w), dy, np.float32)) for dx, dy in shifts]
    outs = list(LiveRestorer(temporal=8, threaded=threaded).restore(frames))
    assert [o.index for o in outs] == list(range(20))
    inner = (slice(8, -8), slice(8, -8))
    for o in outs[1:]:  # frame 0's flow is measured against its output by the default's DIS (the blind estimate's)
        flow = o.bwd_flow_hwc_px[inner]
        dx, dy = shifts[o.index]
        assert abs(float(np.median(flow[..., 0])) + dx) < SHIFT_TOLERANCE_PX
        assert abs(float(np.median(flow[..., 1])) + dy) < SHIFT_TOLERANCE_PX
    bound = _interpolation_bound(scene, SHIFT_TOLERANCE_PX) + 0.5 / 255
    for o in outs[4:-4]:
        got = o.fused.permute(1, 2, 0).numpy()
        assert np.abs(got - scene)[inner].mean() <= bound


def test_known_smooth_tilt_recovered():
    """A smooth tilt (a sine of 128 px period, 1.2 px amplitude: 0.85 px rms) in x, its sign alternating from frame to
    frame: the registered flow of each frame is minus its tilt within 0.2 px rms inside the frame (the live preset's
    flow, its patches 16 px apart at full size, resolves a tilt smooth over ~100 px; at 64 px it is off by 0.3)."""
    scene = _scene(192, 224, seed=2)
    h, w = scene.shape[:2]
    yy = np.arange(h, dtype=np.float32)[:, None].repeat(w, 1)
    tilt = 1.2 * np.sin(2 * np.pi * yy / 128).astype(np.float32)
    zero = np.zeros_like(tilt)
    frames = [_moved(scene, tilt * (1 if i % 2 else -1), zero) for i in range(16)]
    outs = list(LiveRestorer(temporal=8).restore(frames))
    inner = (slice(12, -12), slice(12, -12))
    for o in outs[1:]:
        want = -tilt * (1 if o.index % 2 else -1)
        err = o.bwd_flow_hwc_px[..., 0] - want
        assert float(np.sqrt((err[inner] ** 2).mean())) < 0.2
        assert float(np.abs(o.bwd_flow_hwc_px[..., 1][inner]).mean()) < 0.1


@pytest.mark.parametrize("n", [2, 5, 23])
def test_one_output_per_input_in_order(n):
    """Every input frame gives one output, in order, for clips shorter and longer than the window (float frames)."""
    rng = np.random.default_rng(n)
    frames = [torch.from_numpy(_scene(32, 40, seed=3)).permute(2, 0, 1) * 0.9 + 0.05 * rng.random() for _ in range(n)]
    outs = list(LiveRestorer(temporal=8).restore(frames))
    assert [o.index for o in outs] == list(range(n))
    assert all(o.restored.shape == (3, 32, 40) and o.bwd_flow_px.shape == (2, 32, 40) for o in outs)


@pytest.mark.parametrize("temporal", [4, 8, 9])
def test_latency(temporal):
    """Output t is yielded before input t + L + 1 is read, L = 2·(N − N//2 − 1) (a reference window centred on the
    frame, then the output's: each reaches N − N//2 − 1 frames ahead), and every output once the input ends."""
    frames = [(_scene(24, 32, seed=6) * 255).astype(np.uint8)] * 30
    read = []

    def source():
        for i, f in enumerate(frames):
            read.append(i)
            yield f

    ahead = 2 * (temporal - temporal // 2 - 1)
    for o in LiveRestorer(temporal, threaded=False).restore(source()):
        assert len(read) <= min(len(frames), max(o.index + ahead + 1, temporal + ahead // 2))


def test_threads_change_nothing():
    """The reader and deblur threads change when a step runs, never what it computes: the same outputs to the bit."""
    scene = _scene(seed=4)
    h, w = scene.shape[:2]
    rng = np.random.default_rng(4)
    shifts = rng.normal(0, 0.7, (14, 2)).astype(np.float32)
    frames = [_moved(scene, np.full((h, w), dx), np.full((h, w), dy)) for dx, dy in shifts]
    a = [o.restored.clone() for o in LiveRestorer(6, PhysicsDeblur(2.0, 2.0), threaded=True).restore(frames)]
    b = [o.restored.clone() for o in LiveRestorer(6, PhysicsDeblur(2.0, 2.0), threaded=False).restore(frames)]
    assert all(torch.equal(x, y) for x, y in zip(a, b)) and len(a) == 14


def test_luma_deblur_of_a_grey_frame_is_the_per_channel_one():
    """On a grey frame (R = G = B) the luma is the frame, so the live deblur (the Wiener filter and tone guard on the
    luma, the change added to each channel, the live registration's jitter in the OTF) equals the per-channel filter
    and guard of the default with that jitter."""
    grey = torch.from_numpy(_scene(64, 80, seed=5)[..., 0]).expand(3, 64, 80).contiguous()
    deblur = PhysicsDeblur(2.0, 2.0)
    jittered = PhysicsDeblur(2.0, 2.0, jitter_px=LIVE_JITTER_PX)
    want = tone_guard(grey, jittered(grey))  # under 1 MP: each channel
    got = live_deblurred(deblur, grey)
    assert torch.allclose(got, want, atol=2e-6)


def test_bad_settings_are_one_line_errors():
    with pytest.raises(D2TurbError):
        LiveRestorer(temporal=1)
    with pytest.raises(D2TurbError):
        LiveRestorer(temporal=8, scale=0)
    with pytest.raises(D2TurbError):
        dis_preset("turbo")
    with pytest.raises(D2TurbError, match="at least 2 frames"):
        list(LiveRestorer(temporal=4).restore([np.zeros((20, 20, 3), np.uint8)]))
    with pytest.raises(D2TurbError, match="one size"):
        list(LiveRestorer(temporal=4).restore([np.zeros((20, 20, 3), np.uint8), np.zeros((20, 24, 3), np.uint8)]))


def test_presets_of_the_command_line():
    """``balanced`` is the default and the clip room's DIS "fast" (the default's outputs unchanged), ``fast`` the
    live restorer; the live preset refuses the settings it does not have, in one line."""
    from d2turb.clip import ClipRestorer
    from d2turb.restore.clip_build import ClipOptions, clip_restorer

    assert ClipOptions().preset == "balanced" and PRESETS["balanced"] == "fast"
    restorer, _, _ = clip_restorer("unused", 8, deblur="none")
    assert isinstance(restorer, ClipRestorer) and restorer.preset == "fast"
    live, _, _ = clip_restorer("unused", 8, deblur="none", preset="fast")
    assert isinstance(live, LiveRestorer)
    with pytest.raises(D2TurbError, match="live"):
        clip_restorer("unused", 8, deblur="none", preset="fast", fusion="sharpest")


def test_help_states_the_loss():
    """``restore --help`` says what ``--preset fast`` gives up, in the figure measured (clip.live.LIVE_LOSS_DB)."""
    out = subprocess.run([sys.executable, "-m", "d2turb", "restore", "--help"], capture_output=True, text=True)
    text = " ".join(out.stdout.split())
    assert out.returncode == 0
    assert f"{LIVE_LOSS_DB:.2f} dB" in text and f"{LIVE_LOSS_PLAIN_DB:.2f} dB in plain PSNR" in text
    assert "blind test set" in text
