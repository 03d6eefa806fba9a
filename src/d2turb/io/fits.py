"""FITS images and cubes through astropy (the ``fits`` extra: ``pip install 'd2turb[fits]'``).

The first HDU with image data is read: 2-D, one grey frame; 3-D, a cube of frames along its first axis (NAXIS3) or,
read as one image (:func:`read_fits_image`), an RGB image when that axis has 3 planes; 4-D, frames of 3 colour
planes. Integer data are kept as 8 or 16 bits (astropy applies BZERO: the usual signed 16-bit data with BZERO 32768
read as uint16); floating-point data must lie in [0, 1] (as a float TIFF), or hold whole numbers in 0-65535 (read as
16 bits). Rows are flipped: FITS stores the bottom row first, and viewers (ds9, Siril) show it at the bottom."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from d2turb.errors import D2TurbError
from d2turb.io.read import FLOAT_TOLERANCE

FITS_SUFFIXES = {".fits", ".fit", ".fts"}
FITS_HINT = "install the fits extra: pip install 'd2turb[fits]' (from a checkout: pip install -e '.[fits]')"


def is_fits(path: str | os.PathLike) -> bool:
    return Path(path).suffix.lower() in FITS_SUFFIXES


def _fits_module(path: Path):
    try:
        from astropy.io import fits
    except ImportError as exc:
        raise D2TurbError(f"{path}: reading FITS needs astropy; {FITS_HINT}") from exc
    return fits


def _data(path: Path) -> np.ndarray:
    fits = _fits_module(path)
    if not path.is_file():
        raise D2TurbError(f"{path}: no such file")
    try:
        with fits.open(path, memmap=False) as hdus:
            for hdu in hdus:
                if getattr(hdu, "is_image", False) and hdu.data is not None and hdu.data.ndim >= 2:
                    return np.asarray(hdu.data)
    except (OSError, ValueError, TypeError) as exc:
        raise D2TurbError(f"{path}: cannot read FITS ({exc.__class__.__name__}: {exc})") from exc
    raise D2TurbError(f"{path}: no image in the FITS file")


def _stored(arr: np.ndarray, path: Path) -> np.ndarray:
    """FITS samples as uint8, uint16 or float32 in [0, 1]."""
    if arr.dtype.kind in "ui":
        lo, hi = int(arr.min(initial=0)), int(arr.max(initial=0))
        if lo < 0 or hi > 65535:
            raise D2TurbError(f"{path}: FITS integers span {lo} to {hi}, outside 0-65535")
        return arr.astype(np.uint8 if arr.dtype.itemsize == 1 else np.uint16)
    arr = arr.astype(np.float32)
    if not np.isfinite(arr).all():
        raise D2TurbError(f"{path}: FITS data contain NaN or infinite values")
    lo, hi = float(arr.min(initial=0)), float(arr.max(initial=0))
    if lo >= -FLOAT_TOLERANCE and hi <= 1 + FLOAT_TOLERANCE:
        return np.clip(arr, 0, 1)
    if lo >= 0 and hi <= 65535 and np.array_equal(arr, np.rint(arr)):
        return arr.astype(np.uint16)
    raise D2TurbError(
        f"{path}: FITS floating-point data span {lo:g} to {hi:g}: neither [0, 1] nor whole numbers in 0-65535; "
        "rescale them"
    )


def _frame(plane: np.ndarray) -> np.ndarray:
    """(H,W) or (3,H,W) FITS planes → (H,W) or (H,W,3), top row first."""
    if plane.ndim == 3:
        plane = plane.transpose(1, 2, 0)
    return np.ascontiguousarray(plane[::-1])


def fits_frame_count(path: str | os.PathLike) -> int:
    """Frames of a FITS clip: 1 for an image, NAXIS3 for a cube (4-D: its first axis)."""
    arr = _data(Path(path))
    return 1 if arr.ndim == 2 else arr.shape[0]


def iter_fits(path: str | os.PathLike) -> Iterator[np.ndarray]:
    """The frames of a FITS image or cube: (H,W) grey or (H,W,3), uint8, uint16 or float32 in [0,1].

    Raises:
        D2TurbError: astropy missing (one line naming the extra), no image, values out of range.
    """
    path = Path(path)
    arr = _stored(_data(path), path)
    if arr.ndim == 2:
        yield _frame(arr)
        return
    if arr.ndim == 4 and arr.shape[1] != 3:
        raise D2TurbError(f"{path}: a 4-D FITS clip must hold 3 colour planes a frame, not {arr.shape[1]}")
    if arr.ndim > 4:
        raise D2TurbError(f"{path}: FITS data of {arr.ndim} axes")
    for plane in arr:
        yield _frame(plane)


def read_fits_image(path: str | os.PathLike) -> np.ndarray:
    """One FITS image: (H,W) grey, or (H,W,3) from a cube of 3 planes (else its first plane)."""
    path = Path(path)
    arr = _stored(_data(path), path)
    if arr.ndim == 3 and arr.shape[0] == 3:
        return _frame(arr)
    while arr.ndim > 2:
        arr = arr[0]
    return _frame(arr)
