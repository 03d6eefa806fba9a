"""The clean source images of a paired dataset: the patch check, reading with depth on the full image and the
resize of small images up to the patch (:class:`SourceCache`, :func:`resize_up`, :func:`make_depth_fn`). Used by
make-dataset (:mod:`~d2turb.data.generate`), the datasets that synthesise on the fly and the training packs."""

from __future__ import annotations

import logging
from collections import OrderedDict
from pathlib import Path

import torch
import torch.nn.functional as F

from d2turb.depth import depth_for_image
from d2turb.errors import D2TurbError
from d2turb.io import image_size, read_image

logger = logging.getLogger(__name__)


def check_patch_fits(sources: list[Path], patch: int) -> None:
    """Refuse a patch larger than every source image (all of them would be upsampled, often absurdly):
    reads image headers until one source's short side reaches the patch."""
    largest = 0
    for path in sources:
        try:
            short = min(image_size(path))
        except D2TurbError:  # unreadable: SourceCache reports it when the source is drawn
            continue
        if short >= patch:
            return
        largest = max(largest, short)
    if largest:
        raise D2TurbError(
            f"patch {patch} is larger than every source image (largest short side {largest} px); "
            f"use a patch of {largest} or less, or larger images",
            param="patch",
        )


def resize_up(image: torch.Tensor, patch: int) -> torch.Tensor:
    """Images whose short side is below ``patch`` are resized up (bilinear, aspect kept) to short side = patch."""
    h, w = image.shape[-2:]
    if min(h, w) >= patch:
        return image
    scale = patch / min(h, w)
    size = (max(patch, round(h * scale)), max(patch, round(w * scale)))
    return F.interpolate(image[None], size=size, mode="bilinear", align_corners=False)[0].clamp(0, 1)


def make_depth_fn(spec: str, device=None, is_disparity: bool = False):
    """spec → f(image (3,H,W), path) -> depth (1,H,W) in [0,1] (far = 1), or None for ``none``."""
    if spec == "none":
        return None

    def depth_fn(image: torch.Tensor, path) -> torch.Tensor:
        if spec == "prior" and device is not None:
            image = image.to(device)  # the weight-free prior is plain torch: run it where the simulator runs
        return depth_for_image(spec, path, image, is_disparity=is_disparity, device=device).float().cpu()

    return depth_fn


class SourceCache:
    """Loads source images (+ depth on the full image), skipping corrupt files deterministically."""

    def __init__(self, sources: list[Path], patch: int, depth_fn, size: int = 4):
        self.sources, self.patch, self.depth_fn, self.size = sources, patch, depth_fn, size
        self.cache: OrderedDict[int, tuple] = OrderedDict()
        self.bad: set[int] = set()
        self.small: set[int] = set()  # sources already reported as smaller than the patch

    def get(self, index: int):
        """(source index actually used, image (3,H,W), depth (1,H,W) | None); a corrupt source is
        replaced by the next readable one in the list (same choice in every process)."""
        for step in range(len(self.sources)):
            k = (index + step) % len(self.sources)
            if k in self.bad:
                continue
            if k in self.cache:
                self.cache.move_to_end(k)
                return (k, *self.cache[k])
            try:
                image = read_image(self.sources[k])
            except D2TurbError as exc:
                logger.warning(f"skipping unreadable source {exc}")
                self.bad.add(k)
                continue
            h, w = image.shape[-2:]
            if min(h, w) < self.patch and k not in self.small:
                self.small.add(k)
                logger.warning(f"{self.sources[k]} is {w}x{h}, smaller than the {self.patch}-px patch: resized up")
            depth = (
                None
                if self.depth_fn is None
                else self.depth_fn(image, self.sources[k]).float().reshape(1, *image.shape[-2:])
            )
            image = resize_up(image, self.patch)
            if depth is not None:
                depth = resize_up(depth, self.patch)
            self.cache[k] = (image, depth)
            if len(self.cache) > self.size:
                self.cache.popitem(last=False)
            return k, image, depth
        raise D2TurbError("no readable clean image among the sources")
