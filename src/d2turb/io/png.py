"""Images to files: tensors to 8-bit arrays, the PNG encoder (and libpng's fast path for reading plain 8-bit RGB
PNGs), and :func:`write_image`, atomic in the format of the path's suffix."""

from __future__ import annotations

import os
import struct
import threading
import zlib
from io import BytesIO
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from d2turb.defaults import DEFAULT_PNG_LEVEL
from d2turb.errors import D2TurbError
from d2turb.io.atomic import atomic_path, write_bytes

try:  # a dependency; a checkout run without installing it (the GPU machines' image) writes PNG with Pillow
    import imagecodecs
except ImportError:
    imagecodecs = None

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_ORIENTATION_KEYS = (b"eXIf", b"Raw profile type exif", b"XML:com.adobe.xmp")  # where Pillow looks for one


def decode_plain_png(path: Path, max_pixels: int | None) -> np.ndarray | None:
    """HxWx3 uint8 pixels of an 8-bit RGB PNG (at least 2x2, at most ``max_pixels``; None: no limit) decoded by
    libpng, faster than Pillow; None for any other file, or one that may hold an EXIF orientation (any chunk
    that Pillow reads one from: such files take Pillow's path, which applies it), or one libpng refuses."""
    if imagecodecs is None or path.suffix.lower() != ".png":
        return None
    try:
        data = path.read_bytes()
    except OSError:
        return None
    # signature, IHDR's length and type, width, height, 8 bits, RGB, standard compression and filters, no interlace
    if data[:16] != _PNG_SIGNATURE + b"\x00\x00\x00\x0dIHDR" or data[24:29] != b"\x08\x02\x00\x00\x00":
        return None
    w, h = struct.unpack(">II", data[16:24])
    if min(w, h) < 2 or (max_pixels and w * h > max_pixels) or any(key in data for key in _PNG_ORIENTATION_KEYS):
        return None
    try:
        pixels = imagecodecs.png_decode(data)
    except Exception:  # Pillow's path reports it
        return None
    return pixels if pixels.shape == (h, w, 3) and pixels.dtype == np.uint8 else None


def float_array(tensor: torch.Tensor) -> np.ndarray:
    """A tensor's values as a float32 numpy array, through no torch operator when it already is float32 on
    the CPU (writer threads: a torch operator there starts an OpenMP team of its own, and more OpenMP threads
    than cores slow the main computation's parallel regions)."""
    tensor = tensor.detach().cpu()
    return (tensor if tensor.dtype == torch.float32 else tensor.float()).numpy()


def to_uint8(image: torch.Tensor) -> np.ndarray:
    """(3|1, H, W) or (H, W) float tensor in [0, 1] → C-contiguous HxWx3 (or HxW) uint8 array, rounded to nearest.

    One temporary (a fresh large one per call costs more in page faults than the arithmetic)."""
    arr = float_array(image) * np.float32(255.0)
    np.clip(arr, 0, 255, out=arr)
    np.rint(arr, out=arr)
    if arr.ndim == 3:
        if arr.shape[0] == 1:
            return arr[0].astype(np.uint8)
        out = np.empty(arr.shape[1:] + arr.shape[:1], np.uint8)
        np.copyto(out, arr.transpose(1, 2, 0), casting="unsafe")
        return out
    return arr.astype(np.uint8)


class SharedUint8:
    """:func:`to_uint8` of one image, computed once for consumers in several threads (a clip's PNG writer and its
    mp4 encoder): whichever calls first converts, the others wait for that and share the array (none may change it).
    No caller ever waits for a job that might not run. ``shape``: the array's, known before the conversion."""

    def __init__(self, image: torch.Tensor):
        c, h, w = image.shape[-3:] if image.ndim == 3 else (1, *image.shape)
        self.shape = (h, w) if c == 1 else (h, w, c)
        self._image, self._array, self._lock = image, None, threading.Lock()

    def __call__(self) -> np.ndarray:
        with self._lock:
            if self._array is None:
                self._array, self._image = to_uint8(self._image), None
            return self._array


def _png_chunk(kind: bytes, data) -> bytes:
    return struct.pack(">I", len(data)) + kind + bytes(data) + struct.pack(">I", zlib.crc32(data, zlib.crc32(kind)))


def _encode_png_up(array: np.ndarray, level: int) -> bytes:
    """PNG (spec: w3.org/TR/png-3) with every row filtered by "Up" (bytes minus those of the row above, mod
    256) and deflated by libdeflate."""
    h, w = array.shape[:2]
    colour = {1: 0, 2: 4, 3: 2, 4: 6}[1 if array.ndim == 2 else array.shape[2]]  # grey, +alpha, RGB, RGBA
    depth = 16 if array.dtype == np.uint16 else 8
    rows = np.ascontiguousarray(array, dtype=">u2" if depth == 16 else np.uint8).view(np.uint8).reshape(h, -1)
    filtered = np.empty((h, 1 + rows.shape[1]), np.uint8)  # big-endian samples, for 16 bits
    filtered[:, 0] = 2  # filter type: Up
    filtered[0, 1:] = rows[0]
    np.subtract(rows[1:], rows[:-1], out=filtered[1:, 1:])
    stream = memoryview(imagecodecs.deflate_encode(filtered, level=level))  # zlib format
    idat = b"".join(_png_chunk(b"IDAT", stream[i : i + (1 << 30)]) for i in range(0, len(stream), 1 << 30))
    header = struct.pack(">IIBBBBB", w, h, depth, colour, 0, 0, 0)
    return _PNG_SIGNATURE + _png_chunk(b"IHDR", header) + idat + _png_chunk(b"IEND", b"")


def encode_png(array: np.ndarray, level: int = DEFAULT_PNG_LEVEL) -> bytes:
    """(H, W) or (H, W, 1|2|3|4) uint8 or uint16 array → PNG bytes (GIL released while compressing).

    Level 1 (the default, for speed) filters every row with "Up" and compresses with libdeflate (faster than libpng's
    fastest settings, files a little larger: benchmarks/RESULTS.md). Other levels: libpng's adaptive filters and zlib
    at that level, both through imagecodecs; without imagecodecs, Pillow's encoder (run-length zlib at level 1).
    """
    if not 0 <= level <= 9:
        raise D2TurbError(f"PNG level must be 0-9, got {level}")
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[..., 0]
    if array.size == 0 or array.ndim not in (2, 3) or (array.ndim == 3 and not 2 <= array.shape[2] <= 4):
        raise D2TurbError(f"cannot write an image of shape {tuple(array.shape)} as PNG")
    if imagecodecs is None:
        buffer = BytesIO()
        options = {"compress_type": zlib.Z_RLE} if level == 1 else {}
        Image.fromarray(np.ascontiguousarray(array)).save(buffer, format="PNG", compress_level=level, **options)
        return buffer.getvalue()
    if level == 1 and imagecodecs.DEFLATE.available:
        return _encode_png_up(array, level)
    return imagecodecs.png_encode(np.ascontiguousarray(array), level=level)


def write_image(path: str | os.PathLike, image, png_level: int = DEFAULT_PNG_LEVEL) -> None:
    """Write a (C, H, W) float tensor in [0, 1] (or a :class:`SharedUint8` of one, an HxW[x3] uint8 array, or for
    PNG an HxW uint16 one) as an
    image, atomically, in the format of the path's suffix (PNG when unknown). ``png_level``: zlib level 0-9 for
    PNG (default 1: fast; 9: smallest files)."""
    if isinstance(image, SharedUint8):
        image = image()
    if isinstance(image, torch.Tensor):
        if image.ndim == 4:
            if image.shape[0] != 1:
                raise D2TurbError(f"write_image: expected one image, got a batch of {image.shape[0]}")
            image = image[0]
        image = to_uint8(image)
    path = Path(path)
    fmt = Image.registered_extensions().get(path.suffix.lower(), "PNG")
    if fmt == "PNG":
        write_bytes(path, encode_png(image, png_level))
        return
    with atomic_path(path) as tmp:
        Image.fromarray(image).save(tmp, format=fmt)
