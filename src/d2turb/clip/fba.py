"""Fourier burst accumulation (FBA, ``--fusion fba``): a fusion of registered frames of one scene whose blur differs
from frame to frame.

Delbracio & Sapiro, "Removing camera shake via weighted Fourier burst accumulation", IEEE TIP 24(11), 2015: each
spatial frequency ζ of the output is a weighted mean of the frames' Fourier coefficients,

    û(ζ) = Σ_i w_i(ζ) v̂_i(ζ),   w_i(ζ) = |v̂_i(ζ)|^p / Σ_j |v̂_j(ζ)|^p   (magnitudes smoothed over ζ),

so a frequency is taken mostly from the frames where the blur attenuated it least (p = 0: the plain mean; p → ∞:
the largest coefficient). Under turbulence the short-exposure PSF changes from frame to frame and over the image
(anisoplanatism), so the weights are computed per tile: overlapping tiles with a sin² window (the windows of a 50 %
overlap sum to one, so p = 0 gives back the mean exactly), weights from the magnitude of the grey mean over the
colour channels, applied to every channel. Written here because no maintained library implements FBA.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from d2turb.errors import D2TurbError

FBA_POWER = 4.0  # p; 4 on the validation clips (docs/clips.md); the paper uses 11 for camera shake
FBA_TILE = 64  # px, tiles overlap by half
_SMOOTH_BINS = 1.0  # σ of the Gaussian smoothing of |v̂| over frequency, in frequency bins


def _sin2_window(tile: int) -> np.ndarray:
    w = np.sin(np.pi * (np.arange(tile) + 0.5) / tile) ** 2  # w(x) + w(x + tile/2) = 1
    return np.outer(w, w)[..., None].astype(np.float32)


def fourier_burst_accumulation(stack: list[np.ndarray], power: float = FBA_POWER, tile: int = FBA_TILE) -> np.ndarray:
    """Fuse registered frames by weighted Fourier burst accumulation over overlapping tiles.

    Args:
        stack: N ≥ 1 registered frames of one size, (H, W, C) float arrays.
        power: p ≥ 0 of the weights |v̂|^p (0: the mean).
        tile: tile side in px, even, ≥ 8; tiles overlap by half.

    Returns:
        The fused frame, (H, W, C) float32.
    """
    if not stack:
        raise D2TurbError("Fourier burst accumulation needs at least one frame")
    if not np.isfinite(power) or power < 0:
        raise D2TurbError(f"the FBA power must be finite and >= 0, got {power!r}")
    if tile < 8 or tile % 2:
        raise D2TurbError(f"the FBA tile must be even and >= 8 px, got {tile!r}")
    h, w, c = stack[0].shape
    step = tile // 2
    # reflect-pad so that every pixel is covered by four tiles (two in each direction)
    pad = ((step, step + (-h) % step), (step, step + (-w) % step), (0, 0))
    frames = np.stack([np.pad(np.asarray(s, dtype=np.float32), pad, mode="reflect") for s in stack])
    window = _sin2_window(tile)
    out = np.zeros(frames.shape[1:], dtype=np.float64)
    xs = range(0, frames.shape[2] - tile + 1, step)
    for y in range(0, frames.shape[1] - tile + 1, step):
        # one row of tiles at once: (N, tiles, T, T, C)
        row = np.stack([frames[:, y : y + tile, x : x + tile] for x in xs], axis=1) * window
        spec = np.fft.rfft2(row, axes=(2, 3))
        mag = np.abs(spec).mean(axis=-1)  # (N, tiles, T, T//2+1), grey magnitude
        mag = ndimage.gaussian_filter(  # the rfft axis is a half spectrum: not periodic
            mag, (0, 0, _SMOOTH_BINS, _SMOOTH_BINS), mode=("wrap", "wrap", "wrap", "nearest")
        )
        mag /= mag.max(axis=0, keepdims=True) + 1e-12  # scaled before the power: no overflow
        weight = (mag + 1e-6) ** power  # a frequency no frame holds gets the mean
        weight /= weight.sum(axis=0, keepdims=True)
        fused = np.fft.irfft2((weight[..., None] * spec).sum(axis=0), s=(tile, tile), axes=(1, 2))
        for k, x in enumerate(xs):
            out[y : y + tile, x : x + tile] += fused[k]
    return out[step : step + h, step : step + w].astype(np.float32)
