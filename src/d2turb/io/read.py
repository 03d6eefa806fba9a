"""Reading images: the files and folders named as inputs, robust decoding of odd images (16-bit, float, palette,
EXIF orientation) with a pixel limit against decompression bombs, as float RGB (:func:`read_image`) or as stored
(:func:`read_stored`: 16 bits and grey kept), and header-only sizes."""

from __future__ import annotations

import errno
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageOps, UnidentifiedImageError

from d2turb.defaults import DEFAULT_MAX_PIXELS
from d2turb.errors import D2TurbError
from d2turb.io.atomic import reason
from d2turb.io.formats import PixelFormat, image_format
from d2turb.io.png import decode_plain_png, imagecodecs

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm"}
_limits = {"max_pixels": DEFAULT_MAX_PIXELS}


def cache_dir(*parts: str) -> Path:
    """The user's folder of local weights: ``$D2TURB_CACHE_DIR`` (default ``~/.cache/d2turb``) / parts."""
    return Path(os.environ.get("D2TURB_CACHE_DIR", Path.home() / ".cache" / "d2turb")).expanduser().joinpath(*parts)


def list_images(folder: str | os.PathLike, recursive: bool = False) -> list[Path]:
    """Image files directly inside ``folder`` (with ``recursive``, also in its sub-folders), sorted by path.
    Hidden files and folders (names starting with a dot: our temp files, macOS ``._`` files) are skipped."""
    folder = Path(folder)
    if not folder.is_dir():
        raise D2TurbError(f"{folder}: not a directory")
    try:
        entries = list(folder.rglob("*") if recursive else folder.iterdir())
    except OSError as exc:
        raise D2TurbError(f"{folder}: cannot read folder ({reason(exc)})") from exc
    found = []
    for p in entries:
        hidden = any(part.startswith(".") for part in p.relative_to(folder).parts)
        # a dangling or looping symbolic link is kept: reading it reports it, like any unreadable file
        if not hidden and p.suffix.lower() in IMAGE_SUFFIXES and (p.is_file() or _broken_link(p)):
            found.append(p)
    return sorted(found, key=lambda p: p.relative_to(folder).parts)


def _broken_link(path: Path) -> bool:
    return path.is_symlink() and not path.exists()


def _missing_reason(path: Path) -> str:
    """Why ``path`` is no readable file: a dangling or looping symbolic link, or absent."""
    if path.is_symlink():
        try:
            os.stat(path)
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                return f"{path}: cannot read image (symbolic link loop)"
            return f"{path}: cannot read image (dangling symbolic link to {os.readlink(path)})"
    if path.is_dir():
        return f"{path}: is a folder, not an image file"
    return f"{path}: no such file"


def expand_inputs(inputs: list[str]) -> list[Path]:
    """Files and folders of images on the command line → list of image files."""
    paths: list[Path] = []
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            paths.extend(list_images(p))
        elif p.is_file():
            paths.append(p)
        else:
            raise D2TurbError(_missing_reason(p) if p.is_symlink() else f"{p}: no such file or directory")
    if not paths:
        raise D2TurbError("no input images found")
    for p in paths:
        check_utf8_name(p)
    return paths


def check_utf8_name(path: str | os.PathLike) -> None:
    """Refuse a path that is not valid UTF-8 (bytes a Linux file name may hold, e.g. Latin-1 ``\\xe9``): its
    outputs, messages and JSON records could not name it. Raised before anything is written."""
    text = os.fspath(path)
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        shown = os.fsencode(text).decode("utf-8", "backslashreplace")
        raise D2TurbError(
            f"{shown}: file name is not valid UTF-8; rename it (e.g. convmv -f latin1 -t utf-8) or move it out"
        ) from None


def check_unique_stems(paths: Iterable[str | os.PathLike]) -> None:
    """Per-input outputs are named by the input's stem: refuse inputs that would write the same names
    (``a.png a.jpg``; compared case-insensitively, as some file systems do)."""
    seen: dict[str, list[str]] = {}
    for p in paths:
        seen.setdefault(Path(p).stem.casefold(), []).append(str(p))
    clash = [names for names in seen.values() if len(names) > 1]
    if clash:
        listed = "; ".join(", ".join(names) for names in clash[:3]) + ("; ..." if len(clash) > 3 else "")
        raise D2TurbError(f"several inputs would write the same output names ({listed}); rename or process apart")


FLOAT_TOLERANCE = 1e-3  # float pixels this far outside [0, 1] (rounding of an earlier computation) are clipped


def check_unit_float(arr: np.ndarray, path) -> None:
    """One ``error:`` line for floating-point pixels that are not finite or lie beyond ``FLOAT_TOLERANCE`` of [0, 1]."""
    if not np.isfinite(arr).all():
        raise D2TurbError(f"{path}: image contains NaN or infinite values")
    lo, hi = float(arr.min(initial=0)), float(arr.max(initial=0))
    if lo < -FLOAT_TOLERANCE or hi > 1 + FLOAT_TOLERANCE:
        raise D2TurbError(
            f"{path}: floating-point pixels span {lo:g} to {hi:g}, outside [0, 1]; rescale the image to [0, 1] "
            "(or save it as 8- or 16-bit)"
        )


def _to_float_array(img: Image.Image, path: Path | str = "image") -> np.ndarray:
    """PIL image of any mode → float32 HxWx3 RGB in [0, 1] (alpha dropped, grey replicated).

    Integer images are scaled by their type's maximum (16-bit: 65535; 32-bit: 65535 when a value exceeds 255).
    Float images (TIFF ``F``) must hold finite values in [0, 1]: NaN/inf, or values beyond [0, 1] by more than
    :data:`FLOAT_TOLERANCE` (radiance, a 0-255 or 0-1000 scale), are refused naming the range found, rather than
    clipped into a saturated image."""
    mode = img.mode
    if mode in ("I;16", "I;16B", "I;16L", "I"):
        arr = np.asarray(img, dtype=np.float64)
        lo, hi = float(arr.min(initial=0)), float(arr.max(initial=0))
        if lo < 0 or hi > 65535:
            raise D2TurbError(
                f"{path}: 32-bit integer pixels span {lo:g} to {hi:g}, outside 0-65535; save the image as 8- or 16-bit"
            )
        scale = 65535.0 if hi > 255 or mode.startswith("I;16") else 255.0
        arr = (arr / scale)[..., None].repeat(3, axis=2)
    elif mode == "F":
        arr = np.asarray(img, dtype=np.float64)
        check_unit_float(arr, path)
        arr = arr[..., None].repeat(3, axis=2)
    else:
        if mode not in ("RGB", "L"):
            img = img.convert("RGBA").convert("RGB") if "A" in mode or mode == "P" else img.convert("RGB")
        arr = np.asarray(img.convert("RGB"), dtype=np.float64) / 255.0
    return np.clip(arr, 0.0, 1.0).astype(np.float32)


def set_max_pixels(limit: int | None) -> None:
    """Largest image (width × height) that :func:`read_image` decodes; None or 0 = no limit.

    Bigger headers are refused before decoding (decompression bombs: a tiny file claiming 100000²
    pixels). The CLI sets it from ``--max-pixels``; the default is Pillow's own limit.
    """
    if limit is not None and limit < 0:
        raise D2TurbError(f"set_max_pixels: limit must be >= 0 (0 = no limit), got {limit}")
    _limits["max_pixels"] = limit or None


def open_image(path: str | os.PathLike, max_pixels: int | None = -1) -> Image.Image:
    """Decode an image file with Pillow (EXIF orientation applied), refusing oversized headers.

    Args:
        path: image file.
        max_pixels: pixel limit; -1 (default) = the limit of :func:`set_max_pixels`, None = no limit.

    Returns:
        The loaded PIL image (its file closed).

    Raises:
        D2TurbError: missing, unreadable or corrupt file, or a header larger than the limit.
    """
    path = Path(path)
    if not path.is_file():
        raise D2TurbError(_missing_reason(path))
    limit = _limits["max_pixels"] if max_pixels == -1 else max_pixels
    saved = Image.MAX_IMAGE_PIXELS
    Image.MAX_IMAGE_PIXELS = None  # the limit is applied below, with a message that names the file
    try:
        with Image.open(path) as img:
            w, h = img.size
            if limit and w * h > limit:
                raise D2TurbError(
                    f"{path}: image claims {w}x{h} pixels ({w * h / 1e6:.0f} megapixels), over the limit of "
                    f"{limit / 1e6:.0f} megapixels (decompression-bomb guard); allow it with --max-pixels {w * h}"
                )
            img.load()
            return ImageOps.exif_transpose(img)
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, Image.DecompressionBombError) as exc:
        raise D2TurbError(f"{path}: cannot read image ({exc.__class__.__name__}: {exc})") from exc
    finally:
        Image.MAX_IMAGE_PIXELS = saved


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) from an image file's header, without decoding it (EXIF orientation not applied)."""
    saved = Image.MAX_IMAGE_PIXELS
    Image.MAX_IMAGE_PIXELS = None  # only the header is read
    try:
        with Image.open(path) as img:
            return img.size
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise D2TurbError(f"{path}: cannot read image ({exc.__class__.__name__}: {exc})") from exc
    finally:
        Image.MAX_IMAGE_PIXELS = saved


def _decode(path: Path) -> tuple[np.ndarray | None, Image.Image | None]:
    """(HxWx3 uint8 pixels, None) for an 8-bit RGB image (the common case), else (None, the opened image)."""
    pixels = decode_plain_png(path, _limits["max_pixels"])
    if pixels is not None:
        return pixels, None
    img = open_image(path)
    if img.mode == "RGB" and min(img.size) >= 2:
        return np.asarray(img), None
    return None, img


def read_frame(path: str | os.PathLike) -> np.ndarray | torch.Tensor:
    """An 8-bit RGB image as it is stored, (H, W, 3) uint8 (what clip restoration holds: no float copy, a quarter
    of the memory); any other image as :func:`read_image` gives it. Errors as :func:`read_image`."""
    path = Path(path)
    pixels, img = _decode(path)
    return np.ascontiguousarray(pixels) if pixels is not None else _other_image(path, img)


def read_image(path: str | os.PathLike) -> torch.Tensor:
    """Read an image as a float32 tensor (3, H, W) in [0, 1].

    Grayscale is replicated to RGB, alpha is dropped, 16-bit is scaled by 65535, palette images are
    expanded and EXIF orientation is applied. Corrupt or unreadable files, and headers over the pixel
    limit (:func:`set_max_pixels`), raise ``D2TurbError``.
    """
    path = Path(path)
    pixels, img = _decode(path)
    if pixels is not None:  # the common case, in float32 (x/255 rounds as in float64); numpy: see float_array
        arr = pixels.transpose(2, 0, 1).astype(np.float32, order="C")
        arr /= np.float32(255.0)
        return torch.from_numpy(arr)
    return _other_image(path, img)


def _other_image(path: Path, img: Image.Image) -> torch.Tensor:
    """An image that is not 8-bit RGB (grey, alpha, 16-bit, palette, float) as read_image's (3, H, W) tensor."""
    try:
        arr = _to_float_array(img, path)
    except (OSError, ValueError) as exc:
        raise D2TurbError(f"{path}: cannot read image ({exc.__class__.__name__}: {exc})") from exc
    if arr.shape[0] < 2 or arr.shape[1] < 2:
        raise D2TurbError(f"{path}: image is too small ({arr.shape[1]}x{arr.shape[0]})")
    if not np.isfinite(arr).all():
        raise D2TurbError(f"{path}: image contains NaN or infinite values")
    return torch.from_numpy(np.ascontiguousarray(arr.transpose(2, 0, 1)))


_ORIENT = {  # EXIF orientation → the numpy view that Pillow's exif_transpose gives
    2: lambda a: a[:, ::-1],
    3: lambda a: a[::-1, ::-1],
    4: lambda a: a[::-1],
    5: lambda a: a.swapaxes(0, 1),
    6: lambda a: np.rot90(a, -1),
    7: lambda a: a[::-1, ::-1].swapaxes(0, 1),
    8: lambda a: np.rot90(a, 1),
}


def _float_checked(arr: np.ndarray, path: Path) -> np.ndarray:
    arr = arr.astype(np.float32)
    check_unit_float(arr, path)
    return np.clip(arr, 0, 1)


def read_stored(path: str | os.PathLike) -> np.ndarray:
    """An image as stored: (H,W) grey or (H,W,3) RGB, uint8 or uint16 (float TIFF: float32 in [0,1]); alpha
    dropped, palettes expanded, EXIF orientation applied, 32-bit integers of 8-bit values as uint8.

    Raises:
        D2TurbError: as :func:`~d2turb.io.read_image` (unreadable, over the pixel limit, values out of range).
    """
    path = Path(path)
    pixels = decode_plain_png(path, _limits["max_pixels"])
    if pixels is not None:
        return np.ascontiguousarray(pixels)
    if not path.is_file():
        raise D2TurbError(_missing_reason(path))
    img = open_image(path)  # the limit, the orientation, one-line errors
    if img.mode in ("RGB", "RGBA") and image_format(path) == PixelFormat(3, 16) and imagecodecs is not None:
        try:
            arr = imagecodecs.imread(str(path))
        except Exception as exc:  # noqa: BLE001 - any decoder failure: one line naming the file
            raise D2TurbError(f"{path}: cannot read image ({exc.__class__.__name__}: {exc})") from exc
        arr = arr[..., :3]
        if arr.dtype != np.uint16:
            arr = arr.astype(np.uint16) if arr.dtype.kind in "ui" else _float_checked(arr, path)
        with Image.open(path) as raw:
            orientation = raw.getexif().get(ImageOps.ExifTags.Base.Orientation)
        arr = _ORIENT.get(orientation, lambda a: a)(arr)
    else:
        arr = _pil_stored(img, path)
    if min(arr.shape[:2]) < 2:
        raise D2TurbError(f"{path}: image is too small ({arr.shape[1]}x{arr.shape[0]})")
    return np.ascontiguousarray(arr)


def _pil_stored(img: Image.Image, path: Path) -> np.ndarray:
    mode = img.mode
    if mode in ("I;16", "I;16B", "I;16L", "I;16N"):
        return np.asarray(img).astype(np.uint16)
    if mode == "I":
        arr = np.asarray(img, dtype=np.int64)
        lo, hi = int(arr.min(initial=0)), int(arr.max(initial=0))
        if lo < 0 or hi > 65535:
            raise D2TurbError(
                f"{path}: 32-bit integer pixels span {lo} to {hi}, outside 0-65535; save the image as 8- or 16-bit"
            )
        return arr.astype(np.uint8 if hi <= 255 else np.uint16)
    if mode == "F":
        return _float_checked(np.asarray(img), path)
    if mode in ("1", "L", "LA"):
        return np.asarray(img.convert("L"))
    if mode != "RGB":
        img = img.convert("RGBA").convert("RGB") if "A" in mode or mode == "P" else img.convert("RGB")
    return np.asarray(img)
