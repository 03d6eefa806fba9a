"""Mean optical transfer functions of imaging through Kolmogorov turbulence (Fried 1966; docs/physics.md §4):
the diffraction-limited OTF of a circular aperture times the atmospheric factor, long or short exposure."""

from __future__ import annotations

import math

import torch

from d2turb.errors import D2TurbError


def diffraction_otf(u: torch.Tensor) -> torch.Tensor:
    """T(u) = (2/π)(arccos u − u √(1 − u²)) for u = λν/D ≤ 1, 0 beyond (circular aperture)."""
    u = u.clamp(0, 1)
    return (2 / math.pi) * (torch.arccos(u) - u * torch.sqrt(1 - u * u))


def turbulence_otf(u: torch.Tensor, dr0: float, alpha: float = 1.0) -> torch.Tensor:
    """Mean OTF T(u)·H(u) with H(u) = exp{−3.44 (u·D/r0)^(5/3) [1 − α u^(1/3)]} (docs/physics.md §4).

    Args:
        u: spatial frequency in units of the diffraction cut-off D/λ (λν/D), any shape, ≥ 0.
        dr0: D/r0 at the imaging wavelength.
        alpha: 0 long exposure (tilt kept), 1 tilt removed (near field), 1/2 far field.
    """
    if not math.isfinite(dr0) or dr0 < 0:
        raise D2TurbError(f"D/r0 must be finite and >= 0, got {dr0!r}")
    uc = u.clamp(0, 1)
    h = torch.exp(-3.44 * (uc * dr0) ** (5 / 3) * (1 - alpha * uc ** (1 / 3)))
    return diffraction_otf(u) * h


def pixel_frequency_grid(height: int, width: int, dtype=torch.float64) -> torch.Tensor:
    """|f| in cycles per pixel on the (height, width // 2 + 1) grid of ``torch.fft.rfft2``."""
    fy = torch.fft.fftfreq(height, dtype=dtype)[:, None]
    fx = torch.fft.rfftfreq(width, dtype=dtype)[None, :]
    return torch.sqrt(fx * fx + fy * fy)


def image_otf(height: int, width: int, dr0: float, lambda_over_d_px: float, alpha: float = 1.0) -> torch.Tensor:
    """The mean OTF sampled on an image's rfft2 grid. ``lambda_over_d_px`` = λ/(D·ifov), the diffraction angle in
    pixels (2 at Nyquist sampling), so that u = f · λ/(D·ifov) for f in cycles per pixel."""
    if not math.isfinite(lambda_over_d_px) or lambda_over_d_px <= 0:
        raise D2TurbError(f"λ/D in pixels must be positive and finite, got {lambda_over_d_px!r}")
    u = pixel_frequency_grid(height, width) * lambda_over_d_px
    return turbulence_otf(u, dr0, alpha)
