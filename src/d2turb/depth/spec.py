"""The CLI ``--depth`` spec → a depth map for one image: none, the weight-free prior, Depth Anything V2 from a
local folder, or a measured map (a file, or a folder holding one per image stem).

Convention: relative depth d̃ ∈ [0, 1], far = 1, returned as a float32 tensor (1, H, W).
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from d2turb.depth.anything import DepthAnything
from d2turb.depth.io import find_depth_file, load_depth_for_image
from d2turb.depth.prior import estimate_depth_prior
from d2turb.errors import D2TurbError

_ANYTHING_CACHE: dict[str, object] = {}


def check_depth_spec(spec: str) -> None:
    """Refuse a ``--depth`` spec that cannot work for any image, once, rather than once per image.

    Raises:
        D2TurbError: ``anything:PATH`` without a model folder there, or a FILE/DIR that does not exist.
    """
    if spec in ("none", "prior"):
        return
    if spec.startswith("anything:"):
        folder = Path(spec[len("anything:") :])
        if not (folder / "config.json").is_file():
            raise D2TurbError(
                f"depth {spec}: {folder} is not a Depth Anything model folder (no config.json)", param="depth"
            )
    elif not Path(spec).exists():
        raise D2TurbError(
            f"depth {spec}: no such depth file or folder (or use none, prior, anything:PATH)", param="depth"
        )


def depth_for_image(
    spec: str | None,
    image_path: str | os.PathLike | None,
    image: torch.Tensor,
    is_disparity: bool = False,
    device: str | torch.device | None = None,
) -> torch.Tensor | None:
    """Resolve the CLI depth spec for one image → (1, H, W) in [0, 1] (far = 1), or None for ``none``.

    ``none`` | ``prior`` (weight-free estimate) | ``anything:PATH`` (local Depth Anything V2 folder) |
    FILE (a depth map for this image) | DIR (a folder with a depth file of the image's stem).
    ``is_disparity`` applies to FILE/DIR maps, whose aspect ratio must match the image's within 1 %.
    """
    if image.ndim == 4:
        if image.shape[0] != 1:
            raise D2TurbError(f"depth_for_image: expected one image, got a batch of {image.shape[0]}")
        image = image[0]
    size = tuple(image.shape[-2:])
    if spec is None or spec == "none":
        return None
    if spec == "prior":
        return estimate_depth_prior(image)
    if spec.startswith("anything:"):
        model_dir = spec[len("anything:") :]
        key = f"{model_dir}|{device}"
        if key not in _ANYTHING_CACHE:
            _ANYTHING_CACHE.clear()  # keep at most one model in memory
            _ANYTHING_CACHE[key] = DepthAnything(model_dir, device=device or "cpu")
        return _ANYTHING_CACHE[key](image).cpu()
    p = Path(spec)
    if p.is_dir():
        if image_path is None:
            raise D2TurbError(f"depth folder {p}: needs the image's file name to find its depth map")
        return load_depth_for_image(find_depth_file(p, image_path), size, is_disparity)
    if p.is_file():
        return load_depth_for_image(p, size, is_disparity)
    raise D2TurbError(f"depth spec {spec!r}: expected none, prior, anything:PATH, or an existing depth file or folder")
