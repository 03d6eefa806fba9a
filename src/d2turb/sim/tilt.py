"""Spatial correlation of tilt (angle of arrival) and Gaussian random fields with a given covariance.

Single layer (docs/physics.md §2): c⊥(s) = (I0+I2)(s)/I0(0), c∥(s) = (I0−I2)(s)/I0(0) with
I_n(s) = ∫ z^(−14/3) J_n(2sz) J_2(z)² dz and s = θz/(D(1−z/L)) for a layer at distance z from the
aperture and a point source at range L. A constant-Cn² path averages the layer correlations with
weight (1−z/L)^(5/3).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import torch
from scipy.special import gamma, j0, j1

_S_NUMERIC_MAX = 20.0


def _j2(x: np.ndarray) -> np.ndarray:
    """J2(x) = 2J1(x)/x − J0(x) (series x²/8 − x⁴/96 near 0); much faster than scipy's jv(2, x)."""
    x = np.asarray(x, dtype=np.float64)
    small = x < 1e-2
    xs = np.where(small, 1.0, x)
    return np.where(small, x * x / 8 - x**4 / 96, 2 * j1(xs) / xs - j0(xs))


@lru_cache(maxsize=1)
def _tilt_integrals() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """I0(s), I2(s) on a grid of s in [0, 20] by quadrature (substitution z = u³ removes the z^(-2/3) cusp)."""
    s_grid = np.concatenate(([0.0], np.logspace(-3, math.log10(_S_NUMERIC_MAX), 100)))
    u = np.linspace(0.0, 60.0 ** (1 / 3), 12001)[1:]  # z up to 60: the tail is below 1e-8 of I0(0)
    z = u**3
    base = 3.0 * u**-12 * _j2(z) ** 2  # z^(-14/3) J2(z)² dz/du
    du = u[1] - u[0]
    i0, i2 = np.empty_like(s_grid), np.empty_like(s_grid)
    for k, s in enumerate(s_grid):
        arg = 2 * s * z
        i0[k] = np.trapezoid(base * j0(arg), dx=du) + 0.5 * du * 3 / 64  # + the u→0 end (integrand → 3/64)
        i2[k] = np.trapezoid(base * _j2(arg), dx=du)
    return s_grid, i0, i2


def _large_s(n: int, s: np.ndarray) -> np.ndarray:
    """I_n(s) for s → ∞: only z ≪ 1 counts, J2(z)² ≈ z⁴/64 ⇒ I_n ≈ (2s)^(-1/3)/64 · ∫ t^(-2/3) J_n(t) dt."""
    mellin = 2 ** (-2 / 3) * gamma((n + 1 / 3) / 2) / gamma((n + 5 / 3) / 2)
    return (2 * s) ** (-1 / 3) / 64 * mellin


def layer_tilt_correlation(s) -> tuple[np.ndarray, np.ndarray]:
    """(perpendicular, parallel) tilt correlation for one layer at normalised separation s >= 0."""
    s = np.abs(np.asarray(s, dtype=np.float64))
    s_grid, i0, i2 = _tilt_integrals()
    norm = i0[0]
    # beyond the numeric grid: the asymptotic law, scaled to be continuous at s = 20
    big = np.maximum(s, _S_NUMERIC_MAX)
    a0 = i0[-1] / _large_s(0, _S_NUMERIC_MAX) * _large_s(0, big)
    a2 = i2[-1] / _large_s(2, _S_NUMERIC_MAX) * _large_s(2, big)
    v0 = np.where(s <= _S_NUMERIC_MAX, np.interp(s, s_grid, i0), a0)
    v2 = np.where(s <= _S_NUMERIC_MAX, np.interp(s, s_grid, i2), a2)
    return (v0 + v2) / norm, (v0 - v2) / norm


def path_nodes(geometry: str, layer_z_frac: float = 0.5, n_layers: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """Layer positions t = z/L and normalised weights: Gauss–Legendre on [0, 1] × (1 − t)^(5/3)."""
    if geometry == "layer":
        return np.array([float(layer_z_frac)]), np.array([1.0])
    x, w = np.polynomial.legendre.leggauss(n_layers)
    t = 0.5 * (x + 1)
    w = 0.5 * w * (1 - t) ** (5 / 3)
    return t, w / w.sum()


def tilt_correlation(
    theta_rad, aperture_m: float, path_length_m: float, geometry: str = "path", layer_z_frac: float = 0.5
):
    """(perpendicular, parallel) correlation of tilt at image separation θ (rad) for the chosen geometry."""
    theta = np.abs(np.asarray(theta_rad, dtype=np.float64))
    t, w = path_nodes(geometry, layer_z_frac)
    perp, par = np.zeros_like(theta), np.zeros_like(theta)
    for tk, wk in zip(t, w):
        s = theta * path_length_m * tk / (aperture_m * (1 - tk))
        cp, cl = layer_tilt_correlation(s)
        perp += wk * cp
        par += wk * cl
    return perp, par


def torus_offsets(n: int, spacing: float) -> np.ndarray:
    """Signed minimal-image offsets of a length-n periodic grid, times the spacing."""
    i = np.arange(n)
    return np.where(i <= n // 2, i, i - n) * spacing


def fast_size(n: int) -> int:
    """Smallest 2^a 3^b 5^c >= n (fast FFT length)."""
    best = 1 << (max(n, 1) - 1).bit_length()
    for a in range(best.bit_length()):
        for b in range(12):
            for c in range(8):
                v = (1 << a) * 3**b * 5**c
                if n <= v < best:
                    best = v
    return best


def layer_tilt_spectrum(f: np.ndarray, alpha: float) -> np.ndarray:
    """Scalar spectral density (per unit area in cycles/px) of one layer's normalised tilt; the tensor
    spectrum is this times f̂f̂ᵀ (tilt is a gradient field). ``alpha`` = s per pixel of separation.

    From c∥,⊥ = π∫ κ g(κ)(J0 ∓ J2)(κr) dκ with κr = 2sz: g(κ) = z^(-14/3) J2(z)² / (2πακ I0(0)), z = κ/(2α).
    """
    _, i0, _ = _tilt_integrals()
    kappa = 2 * np.pi * np.asarray(f, dtype=np.float64)
    z = kappa / (2 * alpha)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = np.where(kappa > 0, z ** (-14 / 3) * _j2(z) ** 2 / (2 * np.pi * alpha * kappa * i0[0]), 0.0)
    return 4 * np.pi**2 * g


class VectorFieldSampler:
    """Zero-mean Gaussian tilt fields (2-vectors) on an H×W pixel grid by spectral synthesis on a torus
    of at least embed·H × embed·W pixels, with the exact curl-free tensor spectrum of the layers
    [(alpha_k, weight_k)] (covariance C_ij(r) = c⊥δ_ij + (c∥ − c⊥) r̂_i r̂_j). Each frequency cell
    carries the integral of the spectrum over the cell (sub-sampled near the origin); the zero-frequency
    cell carries the remaining variance, so the per-component variance is exactly 1.
    """

    def __init__(self, height: int, width: int, layers, embed: float = 2.0, sub: int = 9, near: int = 4):
        self.height, self.width = height, width
        gh, gw = fast_size(math.ceil(embed * height)), fast_size(math.ceil(embed * width))
        fy, fx = np.meshgrid(np.fft.fftfreq(gh), np.fft.fftfreq(gw), indexing="ij")
        cell = 1.0 / (gh * gw)

        # radial density of the layer mixture, tabulated as dens·f^(5/3) (finite at f → 0) and interpolated
        f_tab = np.geomspace(1e-7, 0.75, 8000)
        h_tab = sum(w * layer_tilt_spectrum(f_tab, a) for a, w in layers) * f_tab ** (5 / 3)

        def tensor(fy_, fx_):
            f = np.hypot(fx_, fy_)
            with np.errstate(divide="ignore"):
                dens = np.where(f > 0, np.interp(f, f_tab, h_tab) / np.maximum(f, 1e-30) ** (5 / 3), 0.0)
            with np.errstate(divide="ignore", invalid="ignore"):
                ux, uy = np.where(f > 0, fx_ / f, 0.0), np.where(f > 0, fy_ / f, 0.0)
            return dens * ux * ux, dens * ux * uy, dens * uy * uy

        sxx, sxy, syy = (c * cell for c in tensor(fy, fx))
        # cells next to the origin: average over a sub×sub grid inside the cell
        mi = np.unique(np.r_[0 : near + 1, gh - near : gh] % gh)
        ni = np.unique(np.r_[0 : near + 1, gw - near : gw] % gw)
        off = (np.arange(sub) + 0.5) / sub - 0.5
        for m in mi:
            for n in ni:
                if m == 0 and n == 0:
                    continue
                sy_, sx_ = np.meshgrid(fy[m, n] + off / gh, fx[m, n] + off / gw, indexing="ij")
                txx, txy, tyy = tensor(sy_, sx_)
                sxx[m, n], sxy[m, n], syy[m, n] = txx.mean() * cell, txy.mean() * cell, tyy.mean() * cell
        sxx[0, 0], syy[0, 0], sxy[0, 0] = 0.0, 0.0, 0.0
        sxx[0, 0], syy[0, 0] = max(1.0 - sxx.sum(), 0.0), max(1.0 - syy.sum(), 0.0)  # exact unit variance
        sxx, sxy, syy = sxx / sxx.sum(), sxy / np.sqrt(sxx.sum() * syy.sum()), syy / syy.sum()
        self.grid = (gh, gw)
        self.spectrum = np.stack([np.stack([sxx, sxy], -1), np.stack([sxy, syy], -1)], -2)  # (gh, gw, 2, 2)
        # closed-form square root of the PSD 2×2 matrices: (A + √det·I)/√(tr + 2√det)
        sdet = np.sqrt(np.clip(sxx * syy - sxy * sxy, 0, None))
        norm = np.sqrt(np.clip(sxx + syy + 2 * sdet, 1e-300, None))
        root = np.stack([np.stack([sxx + sdet, sxy], -1), np.stack([sxy, syy + sdet], -1)], -2) / norm[..., None, None]
        self.root = torch.from_numpy(root).to(torch.complex64)

    def implied_covariance(self) -> np.ndarray:
        """Covariance tensor (gh, gw, 2, 2) of the generated fields versus pixel offset (torus order)."""
        n = self.grid[0] * self.grid[1]
        return np.fft.ifft2(self.spectrum, axes=(0, 1)).real * n

    def sample(self, count: int, generator: torch.Generator | None = None, device="cpu") -> torch.Tensor:
        """(count, 2, H, W) float32 unit-variance fields; real and imaginary parts give two samples."""
        gh, gw = self.grid
        pairs = (count + 1) // 2
        gen_device = generator.device if generator is not None else torch.device("cpu")
        noise = torch.randn((pairs, gh, gw, 2, 2), generator=generator, device=gen_device).to(device)
        xi = torch.complex(noise[..., 0], noise[..., 1])
        if self.root.device != xi.device:
            self.root = self.root.to(xi.device)
        spec = torch.einsum("hwab,phwb->pahw", self.root, xi)
        field = torch.fft.fft2(spec)[..., : self.height, : self.width]
        return torch.cat([field.real, field.imag], 0)[:count].float()


class ScalarFieldSampler:
    """Independent zero-mean unit-variance Gaussian scalar fields, one per row of ``corrs`` (each a
    covariance function of separation r in pixels), on an H×W grid by circulant embedding."""

    def __init__(self, height: int, width: int, corrs, spacing=(1.0, 1.0), embed: float = 2.0):
        self.height, self.width = height, width
        gh, gw = fast_size(math.ceil(embed * height)), fast_size(math.ceil(embed * width))
        dy, dx = np.meshgrid(torus_offsets(gh, spacing[0]), torus_offsets(gw, spacing[1]), indexing="ij")
        r = np.hypot(dx, dy)
        roots = []
        for corr in corrs:
            spec = np.clip(np.fft.fft2(corr(r)).real, 0, None)
            roots.append(np.sqrt(spec / spec.sum()))  # unit variance: (1/n)Σ spec = C(0) = 1 after normalising
        self.grid = (gh, gw)
        self.root = torch.from_numpy(np.stack(roots)).float()  # (F, gh, gw)

    def sample(self, count: int, generator: torch.Generator | None = None, device="cpu") -> torch.Tensor:
        """(count, F, H, W) float32."""
        gh, gw = self.grid
        pairs = (count + 1) // 2
        gen_device = generator.device if generator is not None else torch.device("cpu")
        noise = torch.randn((pairs, self.root.shape[0], gh, gw, 2), generator=generator, device=gen_device).to(device)
        xi = torch.complex(noise[..., 0], noise[..., 1])
        if self.root.device != xi.device:
            self.root = self.root.to(xi.device)
        field = torch.fft.fft2(self.root * xi)[..., : self.height, : self.width]
        return torch.cat([field.real, field.imag], 0)[:count].float()
