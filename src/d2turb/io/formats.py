"""Pixels as they are stored: grey or colour, 8 or 16 bits (issue 52: 16-bit captures stay 16-bit, monochrome ones
stay monochrome). :class:`PixelFormat` is what the outputs of a clip or an image are written in (:func:`image_format`:
a file's, from its header), and :func:`to_restorer` / :func:`to_stored` convert to and from what the restorers
compute on. :func:`~d2turb.io.read.read_stored` decodes an image as stored."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError

from d2turb.io.png import float_array

_GREY_MODES = {"1", "L", "LA", "I", "I;16", "I;16B", "I;16L", "I;16N", "F"}
_WIDE_MODES = {"I", "I;16", "I;16B", "I;16L", "I;16N", "F"}  # more than 8 bits a sample (or float)


@dataclass(frozen=True)
class PixelFormat:
    """How outputs are stored: ``channels`` 1 (grey) or 3 (RGB), ``bits`` 8 or 16 a sample (16 also for float
    inputs: their precision beyond 8 bits is kept)."""

    channels: int = 3
    bits: int = 8

    @property
    def dtype(self) -> type:
        return np.uint16 if self.bits == 16 else np.uint8

    def describe(self) -> str:
        return f"{self.bits}-bit {'grey' if self.channels == 1 else 'RGB'}"

    def joined(self, other: PixelFormat) -> PixelFormat:
        """The format that holds both (a clip's frames: colour if any is, 16 bits if any is)."""
        return PixelFormat(max(self.channels, other.channels), max(self.bits, other.bits))


RGB8 = PixelFormat(3, 8)


def array_format(arr: np.ndarray) -> PixelFormat:
    """The :class:`PixelFormat` of a stored array: (H,W) or (H,W,1) grey, (H,W,3) RGB; uint8 8 bits, else 16."""
    channels = 1 if arr.ndim == 2 or arr.shape[-1] == 1 else 3
    return PixelFormat(channels, 8 if arr.dtype == np.uint8 else 16)


def _png_depth(path: Path) -> int | None:
    try:
        with open(path, "rb") as f:
            head = f.read(26)
    except OSError:
        return None
    return head[24] if head[:8] == b"\x89PNG\r\n\x1a\n" and len(head) >= 26 else None


def _wide_colour(img: Image.Image, path: Path) -> bool:
    """True for a colour PNG or TIFF with 16-bit samples (Pillow decodes it to 8 bits)."""
    if img.mode not in ("RGB", "RGBA"):
        return False
    if img.format == "PNG":
        return _png_depth(path) == 16
    if img.format == "TIFF":
        bits = img.tag_v2.get(258, (8,))
        return max(bits if isinstance(bits, tuple) else (bits,)) > 8
    return False


def image_format(path: str | os.PathLike) -> PixelFormat | None:
    """The :class:`PixelFormat` of an image file from its header (None when it cannot be read: the reading pass
    reports it)."""
    path = Path(path)
    saved = Image.MAX_IMAGE_PIXELS
    Image.MAX_IMAGE_PIXELS = None  # only the header is read
    try:
        with Image.open(path) as img:
            channels = 1 if img.mode in _GREY_MODES else 3
            wide = img.mode in _WIDE_MODES or _wide_colour(img, path)
            if img.mode == "I":  # 32-bit integers: 8-bit values read as 8 bits (as read_image scales them)
                wide = True
            return PixelFormat(channels, 16 if wide else 8)
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError):
        return None
    finally:
        Image.MAX_IMAGE_PIXELS = saved


def to_restorer(arr: np.ndarray, fmt: PixelFormat) -> np.ndarray:
    """A stored frame as the clip restorer takes it in ``fmt``: (H,W,C) uint8 for 8 bits, else float32 in [0,1];
    C = ``fmt.channels`` (grey replicated into RGB; RGB to grey by the mean of its channels)."""
    arr = np.asarray(arr)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.shape[2] != fmt.channels:
        arr = np.repeat(arr, 3, axis=2) if fmt.channels == 3 else _grey(arr)
    if fmt.bits == 8 and arr.dtype == np.uint8:
        return np.ascontiguousarray(arr)
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(arr.dtype, 1.0)
    out = arr.astype(np.float32)
    out /= np.float32(scale)
    return np.clip(out, 0, 1, out=out)


def _grey(arr: np.ndarray) -> np.ndarray:
    mean = arr.astype(np.float32).mean(axis=2, keepdims=True)
    return np.rint(mean).astype(arr.dtype) if arr.dtype.kind in "ui" else mean


def to_stored(image, fmt: PixelFormat) -> np.ndarray:
    """A (C,H,W) float tensor (or (H,W,C) float array) in [0,1] → (H,W) or (H,W,3) in ``fmt.dtype``, rounded to
    nearest (C=3 into grey: the mean of the channels; C=1 into RGB: replicated)."""
    arr = float_array(image) if isinstance(image, torch.Tensor) else np.asarray(image, dtype=np.float32)
    if isinstance(image, torch.Tensor):
        arr = arr[None] if arr.ndim == 2 else arr
        arr = arr.transpose(1, 2, 0)
    elif arr.ndim == 2:
        arr = arr[..., None]
    if fmt.channels == 1:
        arr = arr[..., 0] if arr.shape[2] == 1 else arr.mean(axis=2)
    elif arr.shape[2] == 1:
        arr = np.repeat(arr, 3, axis=2)
    top = 65535.0 if fmt.bits == 16 else 255.0
    out = np.clip(arr * np.float32(top), 0, top)
    return np.ascontiguousarray(np.rint(out).astype(fmt.dtype))
