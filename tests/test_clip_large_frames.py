"""The clip room's rules for large frames (>= 1 MP, issue 49 acceptance 5): the registration rounds before the last
run DIS one pyramid level coarser (``ClipState.flow_solver_for``), and that coarser flow still recovers a known
smooth warp (the truth: the warp's own inverse); the physics Wiener filter runs on the luma alone (checked against
the per-channel filter on grey frames and against a frame of constant luma)."""

from __future__ import annotations

import cv2
import numpy as np
import torch
from scipy import ndimage

from d2turb.clip.deblur import PhysicsDeblur, luma_deconvolve, wiener_deconvolve, wiener_gain, wiener_padding
from d2turb.clip.fusion import make_fusion
from d2turb.clip.registration import DIS_PRESETS, DenseFlow
from d2turb.clip.state import EARLY_ROUND_COARSER, LAST_ROUND_STRIDE, ClipState


def _scene(n: int, seed: int = 0) -> np.ndarray:
    """A grey scene with structure at several scales, (n, n) uint8."""
    rng = np.random.default_rng(seed)
    img = np.zeros((n, n), np.float32)
    for sigma, weight in ((1.5, 0.5), (4, 1.0), (12, 1.5)):
        img += weight * cv2.GaussianBlur(rng.standard_normal((n, n)).astype(np.float32), (0, 0), sigma) * sigma
    img = (img - img.min()) / (img.max() - img.min())
    return np.rint(img * 255).astype(np.uint8)


def _smooth_field(rng, n: int, sigma: float, rms: float) -> np.ndarray:
    """A smooth random displacement field (n, n, 2) of about ``rms`` px per axis."""
    f = np.stack([ndimage.gaussian_filter(rng.standard_normal((n, n)), sigma, mode="wrap") for _ in range(2)], -1)
    return (f * rms / f.std()).astype(np.float32)


def test_a_coarser_dis_recovers_a_smooth_warp():
    """Frame = img(x + Δ(x)), Δ smooth over ~25 px (2 px rms): the flow of DIS stopped one level above "fast"'s
    finest scale, or with its patches further apart, is the inverse of Δ to within a quarter of its size, as the
    preset's own is."""
    rng = np.random.default_rng(3)
    n = 256
    img = _scene(n)
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    inner = (slice(16, -16), slice(16, -16))
    for coarser, stride in ((0, None), (EARLY_ROUND_COARSER, None), (0, LAST_ROUND_STRIDE["fast"])):
        errs, sizes = [], []
        for _ in range(3):
            delta = _smooth_field(rng, n, 25, 2.0)
            frame = ndimage.map_coordinates(img.astype(np.float64), [yy + delta[..., 1], xx + delta[..., 0]], order=3)
            frame = np.clip(np.rint(frame), 0, 255).astype(np.uint8)
            est = DenseFlow("fast", coarser, stride)(img, frame)  # frame(x + est(x)) ≈ img(x)
            back = [yy - delta[..., 1], xx - delta[..., 0]]  # est(x) = −Δ(x + est(x)) ≈ −Δ(x − Δ(x))
            inv = -np.stack([ndimage.map_coordinates(delta[..., c], back, order=1) for c in (0, 1)], -1)
            errs.append(np.linalg.norm(est - inv, axis=-1)[inner].mean())
            sizes.append(np.linalg.norm(inv, axis=-1)[inner].mean())
        assert np.mean(errs) < 0.25 * np.mean(sizes), (coarser, stride, errs, sizes)


def _state_after_one_frame(h: int, w: int, passes: int = 2) -> ClipState:
    state = ClipState(temporal=4, passes=passes, fusion=make_fusion("mean"), preset="fast", stabilise=False)
    state.hold(np.zeros((h, w, 3), np.uint8))
    return state


def test_early_rounds_of_large_frames_stop_one_level_coarser():
    finest, stride = DIS_PRESETS["fast"]["finest_scale"], DIS_PRESETS["fast"]["patch_stride"]
    large = _state_after_one_frame(1024, 1024)  # 1 MP
    assert large.flow_solver_for(1)._dis.getFinestScale() == finest + EARLY_ROUND_COARSER
    assert large.flow_solver_for(2)._dis.getFinestScale() == finest  # the last round: the preset's scale ...
    assert large.flow_solver_for(2)._dis.getPatchStride() == LAST_ROUND_STRIDE["fast"]  # ... its patches further apart
    small = _state_after_one_frame(1000, 1000)  # under 1 MP: every round the preset's
    assert small.flow_solver_for(1) is small.flow_solver_for(2)
    assert small.flow_solver_for(1)._dis.getFinestScale() == finest
    assert small.flow_solver_for(2)._dis.getPatchStride() == stride
    single = _state_after_one_frame(1024, 1024, passes=1)  # one round is the last round
    assert single.flow_solver_for(1)._dis.getFinestScale() == finest


def test_the_luma_wiener_of_a_grey_frame_is_the_per_channel_one():
    """On frames of >= 1 MP the physics Wiener filter runs on the luma and adds its change to each channel: a grey
    frame (three equal channels, so luma = each channel) comes out as the per-channel filter gives it."""
    rng = np.random.default_rng(5)
    grey = torch.from_numpy(cv2.GaussianBlur(rng.random((1024, 1024)).astype(np.float32), (0, 0), 2))
    image = grey.expand(3, -1, -1).contiguous()
    deblur = PhysicsDeblur(2.0)
    out = deblur(image)  # 1 MP: the luma path
    gain = deblur._gain[(1024, 1024)]
    assert torch.allclose(out, wiener_deconvolve(image, gain), atol=2e-5)
    assert torch.allclose(luma_deconvolve(image, gain), out)


def test_the_luma_wiener_leaves_a_flat_luma_alone():
    """A frame whose luma is constant (its detail all in the colour): the filter of a constant is that constant, so
    the luma path changes nothing."""
    rng = np.random.default_rng(6)
    r = torch.from_numpy(cv2.GaussianBlur(rng.random((256, 320)).astype(np.float32), (0, 0), 2)) * 0.4 + 0.3
    b = torch.full_like(r, 0.5)
    g = (0.5 - 0.299 * r - 0.114 * b) / 0.587  # luma 0.5 everywhere
    image = torch.stack([r, g, b])
    deblur = PhysicsDeblur(2.0)
    deblur(image[:, :8, :8])  # (a gain of another size: the cache keys by size)
    top, bottom, left, right = wiener_padding(256, 320)
    gain = wiener_gain(deblur.otf(256, 320), deblur.balance, (256 + top + bottom, 320 + left + right), deblur.prior)
    assert torch.allclose(luma_deconvolve(image, gain), image, atol=1e-5)
