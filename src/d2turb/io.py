"""Image and file I/O: robust reading of odd images, atomic writes (temp name, then rename)."""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageOps, UnidentifiedImageError

from d2turb.errors import D2TurbError

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm"}


def cache_dir(*parts: str) -> Path:
    """The user's folder of local weights: ``$D2TURB_CACHE_DIR`` (default ``~/.cache/d2turb``) / parts."""
    return Path(os.environ.get("D2TURB_CACHE_DIR", Path.home() / ".cache" / "d2turb")).expanduser().joinpath(*parts)


def list_images(folder: str | os.PathLike) -> list[Path]:
    """Image files directly inside ``folder``, sorted by name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise D2TurbError(f"{folder}: not a directory")
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())


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
            raise D2TurbError(f"{p}: no such file or directory")
    if not paths:
        raise D2TurbError("no input images found")
    return paths


def _to_float_array(img: Image.Image) -> np.ndarray:
    """PIL image of any mode → float32 HxWx3 RGB in [0, 1] (alpha dropped, grey replicated)."""
    mode = img.mode
    if mode in ("I;16", "I;16B", "I;16L", "I"):
        arr = np.asarray(img, dtype=np.float64)
        scale = 65535.0 if arr.max(initial=0) > 255 or mode.startswith("I;16") else 255.0
        arr = (arr / scale)[..., None].repeat(3, axis=2)
    elif mode == "F":
        arr = np.asarray(img, dtype=np.float64)[..., None].repeat(3, axis=2)
    else:
        if mode not in ("RGB", "L"):
            img = img.convert("RGBA").convert("RGB") if "A" in mode or mode == "P" else img.convert("RGB")
        arr = np.asarray(img.convert("RGB"), dtype=np.float64) / 255.0
    return np.clip(arr, 0.0, 1.0).astype(np.float32)


def read_image(path: str | os.PathLike) -> torch.Tensor:
    """Read an image as a float32 tensor (3, H, W) in [0, 1].

    Grayscale is replicated to RGB, alpha is dropped, 16-bit is scaled by 65535, palette images are
    expanded and EXIF orientation is applied. Corrupt or unreadable files raise ``D2TurbError``.
    """
    path = Path(path)
    if not path.is_file():
        raise D2TurbError(f"{path}: no such file")
    try:
        with Image.open(path) as img:
            img.load()
            img = ImageOps.exif_transpose(img)
            arr = _to_float_array(img)
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise D2TurbError(f"{path}: cannot read image ({exc.__class__.__name__}: {exc})") from exc
    if arr.shape[0] < 2 or arr.shape[1] < 2:
        raise D2TurbError(f"{path}: image is too small ({arr.shape[1]}x{arr.shape[0]})")
    if not np.isfinite(arr).all():
        raise D2TurbError(f"{path}: image contains NaN or infinite values")
    return torch.from_numpy(arr).permute(2, 0, 1).contiguous()


def check_image_tensor(x: torch.Tensor, name: str = "image", channels: int | None = None) -> None:
    """Validate a (B, C, H, W) floating tensor without NaN/inf."""
    if not isinstance(x, torch.Tensor):
        raise D2TurbError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if x.ndim != 4:
        raise D2TurbError(f"{name}: expected shape (B, C, H, W), got {tuple(x.shape)}")
    if channels is not None and x.shape[1] != channels:
        raise D2TurbError(f"{name}: expected {channels} channels, got {x.shape[1]}")
    if not x.is_floating_point():
        raise D2TurbError(f"{name}: expected a floating tensor, got {x.dtype}")
    if not torch.isfinite(x).all():
        raise D2TurbError(f"{name}: contains NaN or infinite values")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` only if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def to_uint8(image: torch.Tensor) -> np.ndarray:
    """(3|1, H, W) or (H, W) float tensor in [0, 1] → HxWx3 (or HxW) uint8 array."""
    arr = image.detach().float().cpu().clamp(0, 1).numpy()
    if arr.ndim == 3:
        arr = arr.transpose(1, 2, 0)
        if arr.shape[2] == 1:
            arr = arr[..., 0]
    return np.round(arr * 255.0).astype(np.uint8)


def write_image(path: str | os.PathLike, image: torch.Tensor) -> None:
    """Write a (C, H, W) float tensor in [0, 1] as an 8-bit image, atomically."""
    if image.ndim == 4:
        if image.shape[0] != 1:
            raise D2TurbError(f"write_image: expected one image, got a batch of {image.shape[0]}")
        image = image[0]
    arr = to_uint8(image)
    path = Path(path)
    with atomic_path(path) as tmp:
        Image.fromarray(arr).save(tmp, format=Image.registered_extensions().get(path.suffix.lower(), "PNG"))


def write_npy(path: str | os.PathLike, array: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, array)


def write_json(path: str | os.PathLike, obj) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=2, sort_keys=True) + "\n")


def write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
