"""Spatial correlation of tilt (angle of arrival): the theory the simulator's random fields follow
(:mod:`d2turb.sim.fields` draws them) and turbulence measurement inverts.

Single layer (docs/physics.md §2): c⊥(s) = (I0+I2)(s)/I0(0), c∥(s) = (I0−I2)(s)/I0(0) with
I_n(s) = ∫ z^(−14/3) J_n(2sz) J_2(z)² dz and s = θz/(D(1−z/L)) for a layer at distance z from the
aperture and a point source at range L. A constant-Cn² path averages the layer correlations with
weight (1−z/L)^(5/3).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
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


@lru_cache(maxsize=8)
def _gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    """numpy's Gauss–Legendre nodes and weights on [-1, 1], computed once per n (read-only: shared by callers)."""
    x, w = np.polynomial.legendre.leggauss(n)
    x.flags.writeable = w.flags.writeable = False
    return x, w


def path_nodes(geometry: str, layer_z_frac: float = 0.5, n_layers: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """Layer positions t = z/L and normalised weights: Gauss–Legendre on [0, 1] × (1 − t)^(5/3)."""
    if geometry == "layer":
        return np.array([float(layer_z_frac)]), np.array([1.0])
    x, w = _gauss_legendre(n_layers)
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


@lru_cache(maxsize=1)
def layer_tilt_radial_cdf() -> tuple[np.ndarray, np.ndarray]:
    """(ν, P(ν)/P(∞)): the fraction of one layer's tilt power at spatial frequencies below ν, in cycles per
    unit of the normalised separation s (α = 1 in :func:`layer_tilt_spectrum`). Below ν = 1e-12 the density
    follows its ν^(−5/3) law, so P ∝ ν^(1/3) there."""
    nu = np.geomspace(1e-12, 300.0, 30001)
    dens = layer_tilt_spectrum(nu, 1.0)
    ring = dens * 2 * np.pi * nu
    head = 2 * np.pi * dens[0] * nu[0] ** (5 / 3) * 3 * nu[0] ** (1 / 3)  # ∫_0^ν0 C ρ^(-5/3) 2πρ dρ
    cdf = head + np.concatenate([[0.0], np.cumsum(0.5 * (ring[1:] + ring[:-1]) * np.diff(nu))])
    return nu, cdf / cdf[-1]


# ---- the theory that turbulence measurement inverts (d2turb.clip.strength, docs/measure.md) ------------------------
TILT_VARIANCE_COEF = 0.1816  # Z-tilt variance per axis in (λ/D)² (D/r0)^(5/3) rad² (docs/physics.md §2)


def tilt_variance_px2(dr0, lambda_over_d_px):
    """Z-tilt variance per axis in px²: 0.1816 q² (D/r0)^(5/3) with q = λ/(D·ifov) the diffraction angle in pixels
    (:attr:`Optics.lambda_over_d_px <d2turb.sim.Optics.lambda_over_d_px>`; docs/physics.md §2); only q matters."""
    return TILT_VARIANCE_COEF * lambda_over_d_px**2 * np.asarray(dr0, np.float64) ** (5 / 3)


def dr0_from_tilt_variance(var_px2, lambda_over_d_px):
    """Inverse of :func:`tilt_variance_px2`: D/r0 = (σ² / (0.1816 q²))^(3/5), q = λ/(D·ifov) in pixels."""
    unit = TILT_VARIANCE_COEF * lambda_over_d_px**2
    return (np.clip(np.asarray(var_px2, np.float64), 0, None) / unit) ** (3 / 5)


def _tilt_tensor(s_vec: np.ndarray) -> np.ndarray:
    """Unit tilt covariance C_ij(s) = c⊥ δ_ij + (c∥ − c⊥) ŝ_i ŝ_j of one layer at separation vectors s (…, 2),
    (x, y) order; returns (…, 2) = (C_xx, C_yy)."""
    n = np.hypot(s_vec[..., 0], s_vec[..., 1])
    perp, par = layer_tilt_correlation(n)
    with np.errstate(divide="ignore", invalid="ignore"):
        cx2 = np.where(n > 0, (s_vec[..., 0] / np.where(n > 0, n, 1)) ** 2, 0.5)
    return np.stack([perp + (par - perp) * cx2, perp + (par - perp) * (1 - cx2)], -1)


def differential_tilt_covariance(
    sep_px,
    lags,
    footprint_per_px: float,
    wind_per_frame: float = 0.0,
    wind_dir_deg: float = 0.0,
    boil: float = 0.0,
    geometry: str = "path",
    layer_z_frac: float = 0.5,
    n_layers: int = 16,
) -> np.ndarray:
    """Temporal covariance of the differential tilt u(t) = Δ(x, t) − Δ(x + r, t) of unit-variance tilt, per
    component, under frozen flow with boiling (d2turb.sim.sequence):

        E[u_i(t) u_i(t+τ)] = Σ_k w_k [2 C_ii(β_k ŵ τ) − C_ii(α_k r − β_k ŵ τ) − C_ii(α_k r + β_k ŵ τ)]
                             · (1 − boil)^(|τ|/2)

    with C the I0 ± I2 tensor correlation of one layer (docs/physics.md §2), layer k at t_k = z/L of the path nodes,
    α_k = a·t_k/(1 − t_k) (a = ``footprint_per_px`` = ifov·L/D, s per pixel of image separation) and
    β_k = b/(1 − t_k) (b = ``wind_per_frame`` = v/(fps·D), the wind's shift per frame in aperture diameters).

    Args:
        sep_px: separations r (N, 2) in pixels, (x, y).
        lags: time lags τ (M,) in frames.
    Returns:
        (N, 2, M): covariance of the x and y components of u. At τ = 0 it is the differential-tilt structure
        function 2(1 − c(r)) of the component (c∥ along r, c⊥ across).
    """
    sep = np.asarray(sep_px, dtype=np.float64).reshape(-1, 2)
    lag = np.asarray(lags, dtype=np.float64).reshape(-1)
    t, w = path_nodes(geometry, layer_z_frac, n_layers)
    phi = math.radians(wind_dir_deg)
    wind_hat = np.array([math.cos(phi), math.sin(phi)])  # (x, y), 0 = +x, as simulate-video --wind-dir
    # all layers at once (K, N, M, 2): one _tilt_tensor call instead of three per layer (measure fits ~900 of these
    # per clip); the elementwise arithmetic and the layer sum's order are those of a loop over the layers, so the
    # result is the same to the bit
    alpha = footprint_per_px * t / (1 - t)  # (K,)
    move = (wind_per_frame / (1 - t))[:, None, None] * lag[None, :, None] * wind_hat  # (K, M, 2)
    ar = alpha[:, None, None, None] * sep[None, :, None, :]  # (K, N, 1, 2)
    c_same, c_minus, c_plus = _tilt_tensor(
        np.stack(np.broadcast_arrays(move[:, None], ar - move[:, None], ar + move[:, None]))
    )
    layers = np.moveaxis(2 * c_same - c_minus - c_plus, -1, 2)  # (K, N, 2, M)
    out = np.zeros((len(sep), 2, len(lag)))
    for wk, layer in zip(w, layers):
        out += wk * layer
    return out * (1.0 - boil) ** (np.abs(lag) / 2)
