"""Depth Anything V2 (relative) through ``transformers``, from a local model folder only (never downloads)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from d2turb.depth.io import DEFAULT_MAX_DEPTH_RATIO, depth_from_values
from d2turb.errors import D2TurbError
from d2turb.ops.checks import check_shape

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class DepthAnything:
    """``DepthAnything(path, device)(image (3,H,W) or (B,3,H,W))`` → depth (1,H,W) / (B,1,H,W) in [0,1], far = 1.

    ``path`` is a folder written by ``save_pretrained`` (config.json + weights, optionally
    preprocessor_config.json). The relative models output disparity (near = large); it is inverted
    to depth (depth ∝ 1/disparity, see ``d2turb.depth.io.depth_from_values``) and resized to the image.
    Without a preprocessor config the input is resized (aspect kept, shorter side ``input_size``,
    both sides multiples of 14, bicubic) and ImageNet-normalised.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        device: str | torch.device = "cpu",
        input_size: int = 518,
        max_depth_ratio: float = DEFAULT_MAX_DEPTH_RATIO,
    ):
        path = Path(path)
        if not (path / "config.json").is_file():
            raise D2TurbError(
                f"Depth Anything model folder {path}: not found or has no config.json (give a local folder)"
            )
        try:
            from transformers import AutoModelForDepthEstimation
            from transformers.utils import logging as hf_logging

            hf_logging.disable_progress_bar()
        except ImportError as exc:
            raise D2TurbError("Depth Anything needs the 'transformers' package (pip install d2turb[depth])") from exc
        try:
            # a local folder with local_files_only never reaches the hub: no process-wide HF_HUB_OFFLINE needed
            self.model = AutoModelForDepthEstimation.from_pretrained(path, local_files_only=True).to(device).eval()
        except (OSError, ValueError, KeyError) as exc:
            raise D2TurbError(
                f"Depth Anything model folder {path}: cannot load "
                f"({exc.__class__.__name__}: {str(exc).splitlines()[0]})"
            ) from exc
        self.device, self.input_size, self.max_depth_ratio = torch.device(device), input_size, max_depth_ratio
        self.mean, self.std = IMAGENET_MEAN, IMAGENET_STD
        self.patch = int(getattr(self.model.config, "patch_size", 14))
        pre = path / "preprocessor_config.json"
        if pre.is_file():  # take size/normalisation from the processor config; do the ops in torch
            import json

            cfg = json.loads(pre.read_text())
            size = cfg.get("size", {})
            self.input_size = int(
                size.get("height", size.get("shortest_edge", input_size)) if isinstance(size, dict) else size
            )
            self.mean, self.std = tuple(cfg.get("image_mean", self.mean)), tuple(cfg.get("image_std", self.std))
            self.patch = int(cfg.get("ensure_multiple_of", self.patch))

    def _input_shape(self, h: int, w: int) -> tuple[int, int]:
        scale = self.input_size / min(h, w)
        return tuple(max(self.patch, round(s * scale / self.patch) * self.patch) for s in (h, w))

    @torch.no_grad()
    def disparity(self, image: torch.Tensor) -> torch.Tensor:
        """Raw relative disparity (B,1,H,W) at the image resolution."""
        check_shape(image, "[B] 3 H W", "DepthAnything: RGB image")
        x = image[None] if image.ndim == 3 else image
        if not torch.isfinite(x).all():
            raise D2TurbError("DepthAnything: image contains NaN or infinite values")
        h, w = x.shape[-2:]
        x = x.to(self.device, torch.float32).clamp(0, 1)
        x = F.interpolate(x, size=self._input_shape(h, w), mode="bicubic", align_corners=False).clamp(0, 1)
        mean = torch.tensor(self.mean, device=self.device).view(1, 3, 1, 1)
        std = torch.tensor(self.std, device=self.device).view(1, 3, 1, 1)
        pred = self.model(pixel_values=(x - mean) / std).predicted_depth
        pred = pred[:, None] if pred.ndim == 3 else pred
        return F.interpolate(pred.float(), size=(h, w), mode="bilinear", align_corners=False)

    def __call__(self, image: torch.Tensor) -> torch.Tensor:
        disp = self.disparity(image).cpu().double().numpy()
        depth = np.stack(
            [
                depth_from_values(
                    d[0], is_disparity=True, max_depth_ratio=self.max_depth_ratio, name="Depth Anything output"
                )[None]
                for d in disp
            ]
        )
        out = torch.from_numpy(depth.astype(np.float32))
        return out[0] if image.ndim == 3 else out
