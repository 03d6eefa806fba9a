"""Mean optical transfer functions of imaging through Kolmogorov turbulence (Fried 1966; docs/physics.md §4):
the diffraction-limited OTF of a circular aperture times the atmospheric factor, long or short exposure."""

from __future__ import annotations

import math

import numpy as np
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


def short_exposure_width(dr0: float) -> float:
    """s(D/r0): the σ (in units of λ/D) of the Gaussian whose OTF exp(−2π²s²u²) equals the tilt-removed mean OTF of
    ``sim.otf.turbulence_otf`` (α = 1) where that falls to one half; σ_px = s·λ/(D·ifov). s(0) = 0.468 (Airy)."""

    u = torch.linspace(0.0, 1.0, 4001, dtype=torch.float64)
    otf = turbulence_otf(u, max(float(dr0), 0.0), alpha=1.0).numpy()
    k = int(np.argmax(otf < 0.5))
    u_half = float(np.interp(0.5, [otf[k], otf[k - 1]], [u[k].item(), u[k - 1].item()]))
    return math.sqrt(math.log(2.0) / (2 * math.pi**2)) / u_half
