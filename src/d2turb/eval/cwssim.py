"""CW-SSIM, the complex wavelet structural similarity (Sampat, Wang, Gupta, Bovik, Markey, "Complex Wavelet Structural
Similarity: A New Image Similarity Index", IEEE TIP 18(11), 2009): SSIM's structure term on the coefficients of a
complex steerable pyramid. A small shift of the image turns into a phase change of the coefficients that a local
window barely sees, so the score tolerates the sub-pixel offsets and residual tilt that plain PSNR/SSIM punish
(used on OTIS; docs/metrics.md).

Written here rather than taken from a package: IQA-PyTorch (``pyiqa``, its ``cw_ssim``) pins a newer torch and
pulls ~60 packages (CUDA wheels, transformers, timm), which breaks this project's torch pin, and pyrtools would be a
new dependency for the ~40 lines of one pyramid level. The pyramid is matlabPyrTools' ``buildSCFpyr`` (the
frequency-domain complex steerable pyramid that Sampat's ``cwssim_index.m`` calls), only its coarsest oriented
level (the only one the index reads); the index is ``cwssim_index.m``'s: per orientation, over a 7×7 window,
(2|Σ c₁c₂*| + K) / (Σ|c₁|² + Σ|c₂|² + K), averaged with a Gaussian weight of σ = side/4, then the mean over
orientations. The luma is not rounded to 8-bit levels (pyiqa rounds it). Checked against pyiqa 0.1.16's ``CW_SSIM`` and
pyrtools (tests/test_metrics_cwssim.py, benchmarks/cwssim_oracle.py).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.signal import correlate2d

from d2turb.errors import D2TurbError

LEVELS = 4  # pyiqa's and cwssim_index.m's usual settings: 4 levels, 8 orientations, K = 0, no guard band
ORIENTATIONS = 8
WINDOW = 7
_LUMA = np.array([0.299, 0.587, 0.114])  # Y of YIQ / BT.601, as pyiqa's test_y_channel


def _rcos() -> tuple[np.ndarray, np.ndarray]:
    """matlabPyrTools ``rcosFn(1, -0.5)``: a raised-cosine step from 0 (X ≤ −1) to 1 (X ≥ 0), as a table."""
    size = 256
    x = np.pi * np.arange(-size - 1, 2) / (2 * size)
    y = np.cos(x) ** 2
    y[0], y[-1] = y[1], y[-2]
    return -0.5 + (2 / np.pi) * (x + np.pi / 4), y


def coarsest_bands(grey: np.ndarray, levels: int = LEVELS, orientations: int = ORIENTATIONS) -> list[np.ndarray]:
    """The complex oriented bands of the coarsest level of ``buildSCFpyr(grey, levels, orientations - 1)``.

    Args:
        grey: (H, W) float64 image; min(H, W) must allow ``levels`` octaves (pyiqa's bound: levels ≤ log2(min) − 3).

    Returns:
        ``orientations`` complex128 arrays of about (H, W) / 2^(levels − 1).
    """
    h, w = grey.shape
    if levels > int(math.floor(math.log2(min(h, w)))) - 2 or min(h, w) < 2**levels + WINDOW:
        raise D2TurbError(f"CW-SSIM with {levels} level(s) needs a larger image than {w}x{h}")
    ctr = np.ceil((np.array([h, w]) + 0.5) / 2).astype(int)  # MATLAB's 1-based centre
    xr = (np.arange(1, w + 1) - ctr[1]) / (w / 2)
    yr = (np.arange(1, h + 1) - ctr[0]) / (h / 2)
    xramp, yramp = np.meshgrid(xr, yr)
    angle = np.arctan2(yramp, xramp)
    rad = np.sqrt(xramp**2 + yramp**2)
    rad[ctr[0] - 1, ctr[1] - 1] = rad[ctr[0] - 1, ctr[1] - 2]
    log_rad = np.log2(rad)
    xrcos, yrcos = _rcos()
    yrcos = np.sqrt(yrcos)
    yircos = np.sqrt(np.abs(1 - yrcos**2))
    lodft = np.fft.fftshift(np.fft.fft2(grey)) * np.interp(log_rad, xrcos, yircos)
    for _ in range(levels - 1):  # the finer levels only shrink the low-pass here: their bands are not read
        xrcos = xrcos - 1
        dims = np.array(lodft.shape)
        centre = np.ceil((dims + 0.5) / 2).astype(int)
        lodims = np.ceil((dims - 0.5) / 2).astype(int)
        start = centre - np.ceil((lodims + 0.5) / 2).astype(int)
        sl = (slice(start[0], start[0] + lodims[0]), slice(start[1], start[1] + lodims[1]))
        log_rad, angle, lodft = log_rad[sl], angle[sl], lodft[sl]
        lodft = lodft * np.interp(log_rad, xrcos, yircos)
    xrcos = xrcos - 1
    himask = np.interp(log_rad, xrcos, yrcos)
    lut = 1024
    xcosn = np.pi * np.arange(-(2 * lut + 1), lut + 2) / lut
    order = orientations - 1
    const = 2 ** (2 * order) * math.factorial(order) ** 2 / (orientations * math.factorial(2 * order))
    alpha = np.mod(np.pi + xcosn, 2 * np.pi) - np.pi
    ycosn = 2 * np.sqrt(const) * np.cos(xcosn) ** order * (np.abs(alpha) < np.pi / 2)
    bands = []
    for b in range(orientations):
        anglemask = np.interp(angle, xcosn + np.pi * b / orientations, ycosn)
        banddft = (-1j) ** order * lodft * anglemask * himask
        bands.append(np.fft.ifft2(np.fft.ifftshift(banddft)))
    return bands


def _grey(image) -> np.ndarray:
    arr = image.detach().cpu().double().numpy() if isinstance(image, torch.Tensor) else np.asarray(image, np.float64)
    if arr.ndim == 3:
        arr = np.tensordot(_LUMA, arr[:3], 1) if arr.shape[0] == 3 else arr[0]
    if arr.ndim != 2:
        raise D2TurbError(f"CW-SSIM takes a (3,H,W), (1,H,W) or (H,W) image, got shape {arr.shape}")
    return arr


def cw_ssim(image, reference, k: float = 0.0, levels: int | None = None, orientations: int = ORIENTATIONS) -> float:
    """CW-SSIM of two images of one size (1 = the same structure; near 1 under a shift of a pixel or two).

    Args:
        image, reference: (3,H,W) / (1,H,W) tensors or (H,W) arrays in [0, 1] (colour: the BT.601 luma).
        k: the index's stabilising constant (0 as in pyiqa and the paper's experiments).
        levels: pyramid levels; None: ``LEVELS``, fewer for images under 64 px (as many as fit, at least 1).

    Returns:
        The index, in [0, 1].
    """
    a, b = _grey(image), _grey(reference)
    if a.shape != b.shape:
        raise D2TurbError(f"CW-SSIM needs two images of one size, got {a.shape} and {b.shape}")
    if levels is None:
        levels = min(LEVELS, max(1, int(math.floor(math.log2(max(min(a.shape), 1)))) - 2))
    window = np.ones((WINDOW, WINDOW)) / WINDOW**2
    scores = []
    for b1, b2 in zip(coarsest_bands(a, levels, orientations), coarsest_bands(b, levels, orientations)):
        corr = correlate2d(b1 * np.conj(b2), window, mode="valid")
        var = correlate2d(np.abs(b1) ** 2 + np.abs(b2) ** 2, window, mode="valid")
        index = (2 * np.abs(corr) + k) / np.maximum(var + k, 1e-300)
        scores.append(float((index * _gaussian(b1.shape, index.shape)).sum()))
    return float(np.mean(scores))


def _gaussian(band_shape: tuple[int, int], shape: tuple[int, int]) -> np.ndarray:
    """MATLAB ``fspecial('gaussian', shape, band_shape[0] / 4)``: normalised to sum 1."""
    sigma = band_shape[0] / 4
    y = np.arange(shape[0]) - (shape[0] - 1) / 2
    x = np.arange(shape[1]) - (shape[1] - 1) / 2
    g = np.exp(-(y[:, None] ** 2 + x[None] ** 2) / (2 * sigma**2))
    return g / g.sum()


__all__ = ["cw_ssim", "coarsest_bands"]
