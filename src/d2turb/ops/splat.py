"""Invert a displacement field by density-based forward splatting (Eq. 12's V_bwd from the simulator's Δ).

:func:`invert_flow` turns a forward flow into the backward flow that undoes it, and a backward flow into the
forward one (the inverse of the inverse).

The simulator gives Δ with I_tilt(x) = I(x + Δ(x)) (Eq. 7, ``warp(I, Δ)``). The rectifier needs V
with I_tilt(y + V(y)) = I(y) (Eq. 9, ``warp(I_tilt, V) ≈ I``). Pixel x of I_tilt shows the content
of y = x + Δ(x), so V(y) = x − y = −Δ(x): the value −Δ(x) is splatted to x + Δ(x) with bilinear
weights, the weights are accumulated as a density, and V = Σ w·(−Δ) / Σ w. Holes (density below
``min_density``) are filled by normalised convolution from filled neighbours, then by −Δ.
Everything is differentiable with respect to Δ (bilinear weights and values, ``index_add``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from d2turb.deprecation import warn_once
from d2turb.errors import D2TurbError
from d2turb.ops.checks import check_shape
from d2turb.ops.warp import base_grid, warp


def splat(values: torch.Tensor, flow: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Bilinear forward splatting: add ``values`` (B,C,H,W) at x + flow(x).

    Returns (weighted value sum (B,C,H,W), density = weight sum (B,1,H,W)); targets outside the
    frame are dropped.
    """
    b, c, h, w = values.shape
    pos = base_grid(h, w, flow.device, flow.dtype) + flow
    x0, y0 = pos[:, 0].floor(), pos[:, 1].floor()
    fx, fy = pos[:, 0] - x0, pos[:, 1] - y0
    x0, y0 = x0.long(), y0.long()
    batch_offset = (torch.arange(b, device=flow.device) * (h * w)).view(b, 1, 1)
    vals = values.permute(1, 0, 2, 3).reshape(c, -1)
    acc = values.new_zeros(c, b * h * w)
    den = values.new_zeros(b * h * w)
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        xi, yi = x0 + dx, y0 + dy
        wgt = (fx if dx else 1 - fx) * (fy if dy else 1 - fy)
        inside = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
        wgt = (wgt * inside).reshape(-1)
        idx = (batch_offset + yi.clamp(0, h - 1) * w + xi.clamp(0, w - 1)).reshape(-1)
        acc = acc.index_add(1, idx, vals * wgt)
        den = den.index_add(0, idx, wgt)
    return acc.reshape(c, b, h, w).permute(1, 0, 2, 3), den.reshape(b, 1, h, w)


def _fill_holes(field: torch.Tensor, known: torch.Tensor, fallback: torch.Tensor, iterations: int) -> torch.Tensor:
    """Grow ``field`` into unknown pixels by 3×3 normalised convolution over known neighbours."""
    b, c, h, w = field.shape
    kernel = field.new_ones(1, 1, 3, 3)
    mask = known.to(field.dtype)
    for _ in range(iterations):
        if bool(mask.bool().all()):
            break
        num = F.conv2d((field * mask).reshape(b * c, 1, h, w), kernel, padding=1).reshape(b, c, h, w)
        cnt = F.conv2d(mask, kernel, padding=1)
        grow = (mask == 0) & (cnt > 0)
        field = torch.where(grow, num / cnt.clamp_min(1), field)
        mask = torch.where(grow, torch.ones_like(mask), mask)
    return torch.where(mask.bool(), field, fallback)


def check_flow(flow: torch.Tensor, name: str = "flow") -> None:
    check_shape(flow, "B 2 H W", name, floating=True)
    if not torch.isfinite(flow).all():
        raise D2TurbError(f"{name}: contains NaN or infinite values")


def invert_flow(
    flow: torch.Tensor, min_density: float = 1e-3, fill_iterations: int = 8, refine_iterations: int = 0
) -> torch.Tensor:
    """The inverse displacement field: for Δ with ``warp(I, Δ)`` = J, the V with ``warp(J, V) ≈ I``.

    A forward flow Δ (simulator: I_tilt = warp(I, Δ)) gives the backward flow V (warp(I_tilt, V) ≈ I, Eq. 9); a
    backward flow gives the forward one. flow (B, 2, H, W) in pixels (channel 0 = x). ``min_density``: splatted
    weight below which a pixel is a hole; holes are filled from neighbours (``fill_iterations`` 3×3 steps), then
    by −flow. ``refine_iterations`` > 0 adds fixed-point steps V ← −Δ(y + V) (off by default, see docs/flow.md).
    """
    check_flow(flow, "flow")
    acc, den = splat(-flow, flow)
    known = den > min_density
    v = acc / den.clamp_min(min_density)
    v = _fill_holes(v, known, -flow, fill_iterations)
    for _ in range(refine_iterations):
        v = -warp(flow, v)
    return v


def backward_flow(
    forward_flow: torch.Tensor, min_density: float = 1e-3, fill_iterations: int = 8, refine_iterations: int = 0
) -> torch.Tensor:
    """Deprecated name of :func:`invert_flow` (warns once)."""
    warn_once("backward_flow", "d2turb.ops.backward_flow is deprecated; use d2turb.ops.invert_flow")
    return invert_flow(forward_flow, min_density, fill_iterations, refine_iterations)


class InvertFlow(nn.Module):
    """Module wrapper of :func:`invert_flow`."""

    def __init__(self, min_density: float = 1e-3, fill_iterations: int = 8, refine_iterations: int = 0):
        super().__init__()
        self.min_density, self.fill_iterations, self.refine_iterations = min_density, fill_iterations, refine_iterations

    def forward(self, flow: torch.Tensor) -> torch.Tensor:
        return invert_flow(flow, self.min_density, self.fill_iterations, self.refine_iterations)


class BackwardFlow(InvertFlow):
    """Deprecated name of :class:`InvertFlow` (warns once)."""

    def __init__(self, min_density: float = 1e-3, fill_iterations: int = 8, refine_iterations: int = 0):
        warn_once("BackwardFlow", "d2turb.ops.BackwardFlow is deprecated; use d2turb.ops.InvertFlow")
        super().__init__(min_density, fill_iterations, refine_iterations)
