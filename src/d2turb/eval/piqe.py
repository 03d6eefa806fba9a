"""PIQE (Venkatanath et al., NCC 2015), reproducing MATLAB ``piqe`` (Image Processing Toolbox, R2018b+).

16x16 blocks of the MSCN image; spatially active blocks (variance > 0.1) are scored for noticeable
artifacts (an edge segment of 6 pixels with std < 0.1) and for Gaussian noise (centre/surround std
criterion). Score in [0, 100], lower is better; a flat image scores 100.
"""

from __future__ import annotations

import numpy as np
import torch
from numpy.lib.stride_tricks import sliding_window_view
from scipy import ndimage

from d2turb.eval.niqe import matlab_grey_uint8

BLOCK = 16
ACTIVITY_THRESHOLD = 0.1
IMPAIRED_THRESHOLD = 0.1
SEGMENT = 6


def _gaussian_window(size: int = 7, sigma: float = 7 / 6) -> np.ndarray:
    x = np.arange(size) - (size - 1) / 2
    w = np.exp(-(x[:, None] ** 2 + x[None, :] ** 2) / (2 * sigma**2))
    return w / w.sum()


def piqe_grey(grey: np.ndarray) -> float:
    """PIQE of a 2-D float64 image with integer values 0..255."""
    pad_r, pad_c = -grey.shape[0] % BLOCK, -grey.shape[1] % BLOCK
    im = np.pad(grey, ((0, pad_r), (0, pad_c)), mode="edge")  # MATLAB padarray 'replicate', 'post'
    window = _gaussian_window()
    mu = ndimage.correlate(im, window, mode="nearest")
    sigma = np.sqrt(np.abs(ndimage.correlate(im * im, window, mode="nearest") - mu * mu))
    mscn = (im - mu) / (sigma + 1)

    nr, nc = im.shape[0] // BLOCK, im.shape[1] // BLOCK
    blocks = mscn.reshape(nr, BLOCK, nc, BLOCK).transpose(0, 2, 1, 3).reshape(-1, BLOCK, BLOCK)
    var = blocks.reshape(len(blocks), -1).var(axis=1, ddof=1)
    active = var > ACTIVITY_THRESHOLD
    blocks, var = blocks[active], var[active]

    # noticeable artifacts: any 6-pixel segment of the four block edges with std < threshold
    edges = np.stack([blocks[:, 0, :], blocks[:, :, -1], blocks[:, -1, :], blocks[:, :, 0]], axis=1)
    seg_std = sliding_window_view(edges, SEGMENT, axis=-1).std(axis=-1, ddof=1)
    impaired = (seg_std < IMPAIRED_THRESHOLD).any(axis=(1, 2))

    # Gaussian noise: block std vs ratio of centre to surround std
    centre = blocks[:, :, [7, 8]].transpose(0, 2, 1).reshape(len(blocks), 2 * BLOCK)
    surround = np.delete(blocks, [7, 9], axis=2).reshape(
        len(blocks), (BLOCK - 2) * BLOCK
    )  # MATLAB deletes cols 8 then (new) 9
    with np.errstate(divide="ignore", invalid="ignore"):
        cen_sur = np.nan_to_num(centre.std(axis=1, ddof=1) / surround.std(axis=1, ddof=1), nan=0.0)
        block_sigma = np.sqrt(var)
        beta = np.abs(block_sigma - cen_sur) / np.maximum(block_sigma, cen_sur)
    noisy = block_sigma > 2 * beta

    distortion = (impaired * (1 - var) + noisy * var).sum()
    return float((distortion + 1) / (1 + active.sum()) * 100)  # C = 1


def piqe(image: torch.Tensor) -> torch.Tensor:
    """PIQE of (3, H, W) or (B, 3, H, W) images in [0, 1] → scalar or (B,) float64 tensor (lower is better)."""
    batch = image if image.ndim == 4 else image[None]
    values = torch.tensor([piqe_grey(matlab_grey_uint8(img)) for img in batch], dtype=torch.float64)
    return values if image.ndim == 4 else values[0]
