"""Differentiable backward warping by a dense pixel flow."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from d2turb.errors import D2TurbError
from d2turb.ops.checks import check_shape


def base_grid(height: int, width: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """Pixel coordinates (1, 2, H, W): channel 0 is x (column), channel 1 is y (row)."""
    ys, xs = torch.meshgrid(
        torch.arange(height, device=device, dtype=dtype),
        torch.arange(width, device=device, dtype=dtype),
        indexing="ij",
    )
    return torch.stack((xs, ys))[None]


def sample_at(
    image: torch.Tensor, coords: torch.Tensor, padding_mode: str = "border", mode: str = "bilinear"
) -> torch.Tensor:
    """Sample ``image`` (B, C, H, W) at absolute pixel coordinates ``coords`` (B, 2, h, w), x then y.

    The output is (B, C, h, w); h, w need not equal H, W (e.g. a strip of rows of a large image).
    """
    _, _, h, w = image.shape
    # align_corners=True: -1 and +1 are the centres of the first and last pixels
    gx = coords[:, 0] * (2.0 / max(w - 1, 1)) - 1.0
    gy = coords[:, 1] * (2.0 / max(h - 1, 1)) - 1.0
    grid = torch.stack((gx, gy), dim=-1).to(image.dtype)
    return F.grid_sample(image, grid, mode=mode, padding_mode=padding_mode, align_corners=True)


def warp(image: torch.Tensor, flow: torch.Tensor, padding_mode: str = "border", mode: str = "bilinear") -> torch.Tensor:
    """Sample ``image`` at ``x + flow(x)``: out(x) = image(x + flow(x)).

    image (B, C, H, W); flow (B, 2, H, W) in pixels, channel 0 = x, channel 1 = y, of either direction: a forward
    flow applies the tilt (``tilt = warp(clean, fwd_flow_px)``), a backward flow undoes it
    (``warp(tilt, bwd_flow_px) ≈ clean``). Differentiable with respect to both image and flow.
    """
    check_shape(image, "B C H W", "warp: image")
    check_shape(flow, "B 2 H W", "warp: flow")
    if image.shape[0] != flow.shape[0] or image.shape[-2:] != flow.shape[-2:]:
        raise D2TurbError(f"warp: image {tuple(image.shape)} and flow {tuple(flow.shape)} do not match")
    _, _, h, w = image.shape
    return sample_at(image, base_grid(h, w, flow.device, flow.dtype) + flow, padding_mode, mode)


class Warp(nn.Module):
    """Module wrapper of :func:`warp`."""

    def __init__(self, padding_mode: str = "border", mode: str = "bilinear"):
        super().__init__()
        self.padding_mode, self.mode = padding_mode, mode

    def forward(self, image: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
        return warp(image, flow, self.padding_mode, self.mode)
