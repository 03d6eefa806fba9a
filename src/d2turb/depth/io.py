"""Reading measured or precomputed depth maps (the CLI ``--depth`` spec is resolved in :mod:`d2turb.depth.spec`).

Convention: relative depth d̃ ∈ [0, 1], far = 1, returned as a float32 tensor (1, H, W).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image, UnidentifiedImageError

from d2turb.errors import D2TurbError

DEPTH_SUFFIXES = (".npy", ".png", ".tif", ".tiff", ".pgm")
DEFAULT_MAX_DEPTH_RATIO = 100.0
ASPECT_TOLERANCE = 0.01  # a depth map is stretched to its image only if their aspect ratios agree this well


def read_depth_array(path: str | os.PathLike) -> np.ndarray:
    """Raw depth/disparity values of a file as float64 (H, W): PNG (8/16-bit), TIFF (float), ``.npy``."""
    path = Path(path)
    if not path.is_file():
        raise D2TurbError(f"{path}: no such depth file")
    if path.suffix.lower() == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise D2TurbError(f"{path}: cannot read depth array ({exc.__class__.__name__}: {exc})") from exc
        if arr.ndim == 3 and arr.shape[0] == 1:
            arr = arr[0]
        if arr.ndim != 2 or not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
            raise D2TurbError(f"{path}: expected a 2-D (or 1xHxW) numeric depth array, got {arr.dtype} {arr.shape}")
        return arr.astype(np.float64)
    try:
        with Image.open(path) as img:
            img.load()
            arr = np.asarray(img)
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, Image.DecompressionBombError) as exc:
        raise D2TurbError(f"{path}: cannot read depth image ({exc.__class__.__name__}: {exc})") from exc
    if arr.ndim == 3:  # grey stored as RGB(A): accept only if the colour channels agree
        rgb = arr[..., :3]
        if not (np.array_equal(rgb[..., 0], rgb[..., 1]) and np.array_equal(rgb[..., 0], rgb[..., 2])):
            raise D2TurbError(f"{path}: depth image is colour-mapped; give a single-channel PNG or a .npy array")
        arr = rgb[..., 0]
    return arr.astype(np.float64)


def _fill_nearest(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Replace invalid pixels by the nearest valid value (sparse LiDAR / stereo maps)."""
    if valid.all():
        return values
    from scipy import ndimage

    _, (iy, ix) = ndimage.distance_transform_edt(~valid, return_indices=True)
    return values[iy, ix]


def normalize_depth(depth: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Min/max over valid pixels → [0, 1] (far = 1). A constant map means one distance: all far (= 1),
    i.e. uniform, flat-field turbulence."""
    valid = np.isfinite(depth) if valid is None else valid
    lo, hi = depth[valid].min(), depth[valid].max()
    if hi - lo <= 1e-12 * max(abs(hi), 1.0):
        return np.ones_like(depth)
    return np.clip((depth - lo) / (hi - lo), 0.0, 1.0)


def depth_from_values(
    values: np.ndarray,
    is_disparity: bool = False,
    max_depth_ratio: float = DEFAULT_MAX_DEPTH_RATIO,
    name: str = "depth",
) -> np.ndarray:
    """Raw depth (or disparity) values → relative depth in [0, 1], far = 1.

    Values ≤ 0 mean "no measurement" (KITTI convention) and are filled from the nearest valid pixel.
    Disparity is inverted (depth ∝ 1/disparity); disparities below max/``max_depth_ratio`` are clamped
    there, so an affine-invariant disparity whose sky is ≈ 0 does not squash the scene to 0.
    """
    if not np.isfinite(values).all():
        raise D2TurbError(f"{name}: depth map contains NaN or infinite values")
    valid = values > 0
    if not valid.any():
        raise D2TurbError(f"{name}: depth map has no valid (positive) values")
    if is_disparity:
        floor = values[valid].max() / max_depth_ratio
        depth = 1.0 / np.maximum(values, floor)
    else:
        depth = values
    depth = _fill_nearest(depth, valid)
    return normalize_depth(depth)


def resize_depth(depth: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """(1, H, W) or (B, 1, H, W) → same rank at ``size``, bilinear (antialiased when shrinking)."""
    size = (int(size[0]), int(size[1]))
    if tuple(depth.shape[-2:]) == size:
        return depth
    x = depth[None] if depth.ndim == 3 else depth
    shrink = size[0] < x.shape[-2] or size[1] < x.shape[-1]
    x = F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=shrink).clamp(0.0, 1.0)
    return x[0] if depth.ndim == 3 else x


def load_depth(
    path: str | os.PathLike,
    size: tuple[int, int] | None = None,
    is_disparity: bool = False,
    max_depth_ratio: float = DEFAULT_MAX_DEPTH_RATIO,
) -> torch.Tensor:
    """Load a depth (or, with ``is_disparity``, an inverse-depth) map → float32 (1, H, W) in [0, 1], far = 1.

    PNG (8/16-bit, raw values; any positive scale works since the map is min/max normalised), TIFF,
    or ``.npy`` (H, W) / (1, H, W). Zeros/negatives = no measurement, filled from the nearest valid
    pixel. ``size=(H, W)`` resizes to the image. NaN/inf → ``D2TurbError``; constant map → all 1.
    """
    depth = depth_from_values(read_depth_array(path), is_disparity, max_depth_ratio, name=str(path))
    out = torch.from_numpy(depth.astype(np.float32))[None]
    return resize_depth(out, size) if size is not None else out


def load_depth_for_image(path: str | os.PathLike, size: tuple[int, int], is_disparity: bool = False) -> torch.Tensor:
    """:func:`load_depth` resized to an image of ``size=(H, W)``; refuses a map whose aspect ratio differs from
    the image's by more than 1 % (a map of another image, or of the unrotated EXIF photo), which a resize would
    silently stretch."""
    depth = load_depth(path, is_disparity=is_disparity)
    h, w = depth.shape[-2:]
    height, width = size
    mismatch = abs((w * height) / (h * width) - 1.0)
    if mismatch > ASPECT_TOLERANCE:
        raise D2TurbError(
            f"{path}: depth map is {w}x{h} but its image is {width}x{height} (aspect ratios differ by "
            f"{100 * mismatch:.1f} %, more than {100 * ASPECT_TOLERANCE:g} %); crop or pad the map to the image's shape"
        )
    return resize_depth(depth, size)


def find_depth_file(folder: str | os.PathLike, image_path: str | os.PathLike) -> Path:
    """The depth file in ``folder`` with the same stem as ``image_path``."""
    folder, image_path = Path(folder), Path(image_path)
    for suffix in DEPTH_SUFFIXES:
        for candidate in (folder / (image_path.stem + suffix), folder / (image_path.stem + suffix.upper())):
            if candidate.is_file():
                return candidate
    raise D2TurbError(
        f"{image_path.name}: no depth file named {image_path.stem}.* ({'/'.join(DEPTH_SUFFIXES)}) in {folder}"
    )
