"""NIQE (Mittal, Soundararajan & Bovik, IEEE SPL 2013) reproducing the original MATLAB release.

MATLAB-exact details: grey via ``rgb2gray`` weights on the 8-bit image (rounded as MATLAB does for
uint8), crop to a multiple of 96, MSCN with the 7x7 Gaussian window and C=1 ('replicate' padding),
18 AGGD features per 96x96 block (48x48 at the second scale), ``imresize(., 0.5)`` (bicubic with
antialiasing), moment-matching fits on the grid 0.2:0.001:10, sample covariance and a ``pinv``
Mahalanobis distance to the pristine model shipped in ``d2turb/resources``.

One deliberate deviation from floating-point MATLAB: in perfectly flat 7x7 patches the MSCN value is
set to exactly 0 (its exact-arithmetic value) instead of +-1e-14 round-off noise whose sign depends on
the filter implementation; the noise changes the AGGD left/right counts (NIQE of I19 by ~0.4).
"""

from __future__ import annotations

import functools
from importlib import resources

import numpy as np
import torch
from scipy import ndimage
from scipy.special import gamma as gamma_fn

from d2turb.errors import D2TurbError

# MATLAB rgb2gray: first row of inv(NTSC RGB->YIQ matrix), i.e. 0.2989, 0.5870, 0.1140 at full precision.
# The full precision matters: the documented 4-digit weights move NIQE of I03 by 0.17.
MATLAB_GREY_WEIGHTS = tuple(
    float(w) for w in np.linalg.inv([[1.0, 0.956, 0.621], [1.0, -0.272, -0.647], [1.0, -1.106, 1.703]])[0]
)
BLOCK = 96
_GAMMA_GRID = 0.2 + 0.001 * np.arange(9801)  # MATLAB 0.2:0.001:10
_R_GAMMA = gamma_fn(2 / _GAMMA_GRID) ** 2 / (gamma_fn(1 / _GAMMA_GRID) * gamma_fn(3 / _GAMMA_GRID))


@functools.lru_cache(maxsize=1)
def pristine_model() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mu (36,), cov (36, 36), gaussian window (7, 7)) of the LIVE pristine model."""
    with resources.as_file(resources.files("d2turb") / "resources" / "niqe_pristine_params.npz") as path:
        params = np.load(path)
        return params["mu_pris_param"].ravel(), params["cov_pris_param"], params["gaussian_window"]


def matlab_grey_uint8(image: torch.Tensor | np.ndarray) -> np.ndarray:
    """(3|1, H, W) in [0, 1] → float64 (H, W) with integer values 0..255, like MATLAB ``rgb2gray`` on uint8."""
    arr = image.detach().cpu().double().numpy() if isinstance(image, torch.Tensor) else np.asarray(image, np.float64)
    if arr.ndim != 3 or arr.shape[0] not in (1, 3):
        raise D2TurbError(f"expected an image of shape (3, H, W) or (1, H, W), got {arr.shape}")
    rgb = np.round(np.clip(arr, 0, 1) * 255.0)  # the 8-bit image the metric is defined on
    if rgb.shape[0] == 1:
        return rgb[0]
    grey = np.tensordot(np.array(MATLAB_GREY_WEIGHTS), rgb, axes=1)
    return np.floor(grey + 0.5)  # uint8 conversion rounds half up for positive values


def _cubic(x: np.ndarray) -> np.ndarray:
    """MATLAB's bicubic kernel (a = -0.5)."""
    ax = np.abs(x)
    return (1.5 * ax**3 - 2.5 * ax**2 + 1) * (ax <= 1) + (-0.5 * ax**3 + 2.5 * ax**2 - 4 * ax + 2) * (
        (ax > 1) & (ax <= 2)
    )


def _resize_matrix(in_len: int, scale: float) -> np.ndarray:
    """(out_len, in_len) matrix applying MATLAB ``imresize`` bicubic along one axis (antialiased when shrinking)."""
    out_len = int(np.ceil(in_len * scale))
    width = 4.0
    kernel = _cubic
    if scale < 1:
        kernel = lambda x: scale * _cubic(scale * x)  # noqa: E731
        width /= scale
    u = np.arange(1, out_len + 1) / scale + 0.5 * (1 - 1 / scale)
    left = np.floor(u - width / 2)
    taps = int(np.ceil(width)) + 2
    idx = left[:, None] + np.arange(taps)[None, :]
    w = kernel(u[:, None] - idx)
    w /= w.sum(axis=1, keepdims=True)
    mirror = np.concatenate([np.arange(in_len), np.arange(in_len)[::-1]])  # symmetric padding
    idx = mirror[np.mod(idx.astype(np.int64) - 1, 2 * in_len)]
    mat = np.zeros((out_len, in_len))
    np.add.at(mat, (np.repeat(np.arange(out_len), taps), idx.ravel()), w.ravel())
    return mat


def imresize(image: np.ndarray, scale: float) -> np.ndarray:
    """MATLAB ``imresize(image, scale)`` (bicubic, antialiasing) for a 2-D float64 array; rows first."""
    rows = _resize_matrix(image.shape[0], scale)
    cols = _resize_matrix(image.shape[1], scale)
    return rows @ image @ cols.T


def _aggd_fit(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Moment-matching AGGD fit per row of ``x`` (N, n) → (alpha, beta_left, beta_right) (Eq. of Lasmar et al.)."""
    neg, pos = x < 0, x > 0
    left_std = np.sqrt((x**2 * neg).sum(1) / neg.sum(1))
    right_std = np.sqrt((x**2 * pos).sum(1) / pos.sum(1))
    gamma_hat = left_std / right_std
    r_hat = np.abs(x).mean(1) ** 2 / (x**2).mean(1)
    r_norm = r_hat * (gamma_hat**3 + 1) * (gamma_hat + 1) / (gamma_hat**2 + 1) ** 2
    alpha = _GAMMA_GRID[np.argmin((_R_GAMMA[None, :] - r_norm[:, None]) ** 2, axis=1)]
    ratio = np.sqrt(gamma_fn(1 / alpha) / gamma_fn(3 / alpha))
    return alpha, left_std * ratio, right_std * ratio


def _block_features(mscn: np.ndarray, block: int) -> np.ndarray:
    """18 NIQE features per non-overlapping block → (n_blocks, 18); blocks in MATLAB column-major order."""
    nr, nc = mscn.shape[0] // block, mscn.shape[1] // block
    blocks = (
        mscn[: nr * block, : nc * block].reshape(nr, block, nc, block).transpose(2, 0, 1, 3).reshape(-1, block, block)
    )
    alpha, bl, br = _aggd_fit(blocks.reshape(len(blocks), -1))
    feats = [alpha, (bl + br) / 2]
    for shift in ((0, 1), (1, 0), (1, 1), (1, -1)):  # MATLAB circshift within the block
        pair = (blocks * np.roll(blocks, shift, axis=(1, 2))).reshape(len(blocks), -1)
        alpha, bl, br = _aggd_fit(pair)
        mean = (br - bl) * gamma_fn(2 / alpha) / gamma_fn(1 / alpha)
        feats += [alpha, mean, bl, br]
    return np.stack(feats, axis=1)


def niqe_features(grey: np.ndarray, window: np.ndarray) -> np.ndarray:
    """(n_blocks, 36) features of a 2-D image with values 0..255 (two scales)."""
    h, w = (grey.shape[0] // BLOCK) * BLOCK, (grey.shape[1] // BLOCK) * BLOCK
    if h == 0 or w == 0:
        raise D2TurbError(
            f"NIQE needs an image of at least {BLOCK}x{BLOCK} pixels, got {grey.shape[1]}x{grey.shape[0]}"
        )
    im = grey[:h, :w]
    per_scale = []
    for scale in (1, 2):
        mu = ndimage.correlate(im, window, mode="nearest")
        sigma = np.sqrt(np.abs(ndimage.correlate(im * im, window, mode="nearest") - mu * mu))
        centred = im - mu
        centred[np.abs(centred) <= 1e-10 * (np.abs(im) + 1)] = 0.0  # flat patches: exactly 0, not round-off noise
        per_scale.append(_block_features(centred / (sigma + 1), BLOCK // scale))  # MSCN, C = 1
        im = imresize(im, 0.5)
    return np.concatenate(per_scale, axis=1)


def niqe_grey(grey: np.ndarray) -> float:
    """NIQE of a 2-D float64 image with values in 0..255."""
    mu_p, cov_p, window = pristine_model()
    with np.errstate(divide="ignore", invalid="ignore"):
        feats = niqe_features(grey, window)
    complete = feats[np.isfinite(feats).all(axis=1)]  # flat blocks have undefined fits (MATLAB nanmean/nancov)
    if len(complete) < 2:
        raise D2TurbError(
            f"NIQE needs at least two textured {BLOCK}x{BLOCK} blocks; the "
            f"{grey.shape[1]}x{grey.shape[0]} image has {len(complete)}"
        )
    d = mu_p - np.nanmean(np.where(np.isfinite(feats), feats, np.nan), axis=0)
    cov = np.cov(complete, rowvar=False)
    return float(np.sqrt(d @ np.linalg.pinv((cov_p + cov) / 2) @ d))


def niqe(image: torch.Tensor) -> torch.Tensor:
    """NIQE of (3, H, W) or (B, 3, H, W) images in [0, 1] → scalar or (B,) float64 tensor (lower is better)."""
    batch = image if image.ndim == 4 else image[None]
    values = torch.tensor([niqe_grey(matlab_grey_uint8(img)) for img in batch], dtype=torch.float64)
    return values if image.ndim == 4 else values[0]
