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


def _psd_root(sxx: np.ndarray, sxy: np.ndarray, syy: np.ndarray) -> np.ndarray:
    """Closed-form square root of PSD 2×2 matrices [[sxx, sxy], [sxy, syy]]: (A + √det·I)/√(tr + 2√det)."""
    sdet = np.sqrt(np.clip(sxx * syy - sxy * sxy, 0, None))
    norm = np.sqrt(np.clip(sxx + syy + 2 * sdet, 1e-300, None))
    return np.stack([np.stack([sxx + sdet, sxy], -1), np.stack([sxy, syy + sdet], -1)], -2) / norm[..., None, None]


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


class VectorFieldSampler:
    """Zero-mean Gaussian tilt fields (2-vectors) on an H×W pixel grid by spectral synthesis on a torus
    of at least embed·H × embed·W pixels, with the exact curl-free tensor spectrum of the layers
    [(alpha_k, weight_k)] (covariance C_ij(r) = c⊥δ_ij + (c∥ − c⊥) r̂_i r̂_j). Each frequency cell
    carries the integral of the spectrum over the cell (sub-sampled near the origin).

    Subharmonics (Lane et al. 1992, extended as in Johansson & Gavel 1994 so that the first grid
    frequencies are refined too): the central (2·block+1)² cells of the torus grid are left out of the FFT
    and synthesised directly at non-periodic frequencies on ``levels`` nested grids, each 3× finer than
    the one before; a level's central block is refined by the next. The zero-frequency cell of the last
    level carries the remaining variance, so the per-component variance is exactly 1. Without them the
    periodic synthesis overshoots the correlation near separations of half the torus period.
    """

    def __init__(
        self,
        height: int,
        width: int,
        layers,
        embed: float = 2.0,
        sub: int = 9,
        near: int = 4,
        block: int = 4,
        levels: int = 2,
    ):
        self.height, self.width = height, width
        gh, gw = fast_size(math.ceil(embed * height)), fast_size(math.ceil(embed * width))
        fy, fx = np.meshgrid(np.fft.fftfreq(gh), np.fft.fftfreq(gw), indexing="ij")
        cell = 1.0 / (gh * gw)

        # radial density of the layer mixture, tabulated as dens·f^(5/3) (finite at f → 0) and interpolated
        f_tab = np.geomspace(1e-9, 0.75, 9000)
        h_tab = sum(w * layer_tilt_spectrum(f_tab, a) for a, w in layers) * f_tab ** (5 / 3)

        def tensor(fy_, fx_):
            f = np.hypot(fx_, fy_)
            with np.errstate(divide="ignore"):
                dens = np.where(f > 0, np.interp(f, f_tab, h_tab) / np.maximum(f, 1e-30) ** (5 / 3), 0.0)
            with np.errstate(divide="ignore", invalid="ignore"):
                ux, uy = np.where(f > 0, fx_ / f, 0.0), np.where(f > 0, fy_ / f, 0.0)
            return dens * ux * ux, dens * ux * uy, dens * uy * uy

        off = (np.arange(sub) + 0.5) / sub - 0.5

        def cell_mean(cy, cx, dy, dx):
            """Mean of the tensor density over cells centred at (cy, cx) of size dy × dx (sub×sub midpoints)."""
            sy_ = cy[..., None, None] + off[:, None] * dy
            sx_ = cx[..., None, None] + off[None, :] * dx
            return [t.mean((-2, -1)) for t in tensor(sy_, sx_)]

        sxx, sxy, syy = (c * cell for c in tensor(fy, fx))
        # cells next to the origin: average over a sub×sub grid inside the cell
        mi = np.unique(np.r_[0 : near + 1, gh - near : gh] % gh)
        ni = np.unique(np.r_[0 : near + 1, gw - near : gw] % gw)
        near_cells = cell_mean(fy[np.ix_(mi, ni)], fx[np.ix_(mi, ni)], 1.0 / gh, 1.0 / gw)
        for arr, val in zip((sxx, sxy, syy), near_cells):
            arr[np.ix_(mi, ni)] = val * cell
        # the central block goes to the subharmonic levels (levels = 0: plain periodic synthesis)
        block = block if levels > 0 else 0
        bi, bj = np.r_[0 : block + 1, gh - block : gh] % gh, np.r_[0 : block + 1, gw - block : gw] % gw
        for arr in (sxx, sxy, syy):
            arr[np.ix_(bi, bj)] = 0.0
        self.sub_freqs, sub_spec = [], []
        idx = np.arange(-(3 * block + 1), 3 * block + 2)
        for level in range(1, levels + 1):
            dy, dx = 1.0 / (gh * 3**level), 1.0 / (gw * 3**level)
            cy, cx = np.meshgrid(idx * dy, idx * dx, indexing="ij")
            txx, txy, tyy = (t * dy * dx for t in cell_mean(cy, cx, dy, dx))
            inner = (np.abs(idx)[:, None] <= block) & (np.abs(idx)[None, :] <= block)
            if level < levels:
                txx[inner], txy[inner], tyy[inner] = 0.0, 0.0, 0.0
            else:
                c = len(idx) // 2
                txx[c, c], txy[c, c], tyy[c, c] = 0.0, 0.0, 0.0
            self.sub_freqs.append((idx * dy, idx * dx))
            sub_spec.append([txx, txy, tyy])
        # exact unit variance: the zero frequency of the last level carries what the cells miss
        dc_x, dc_y = (sub_spec[-1][0], sub_spec[-1][2]) if levels > 0 else (sxx, syy)
        c = len(idx) // 2 if levels > 0 else 0
        total_x = sxx.sum() + sum(s[0].sum() for s in sub_spec)
        total_y = syy.sum() + sum(s[2].sum() for s in sub_spec)
        dc_x[c, c], dc_y[c, c] = max(1.0 - total_x, 0.0), max(1.0 - total_y, 0.0)
        nx = sxx.sum() + sum(s[0].sum() for s in sub_spec)
        ny = syy.sum() + sum(s[2].sum() for s in sub_spec)
        scale = np.array([[1 / nx, 1 / np.sqrt(nx * ny)], [1 / np.sqrt(nx * ny), 1 / ny]])
        self.grid = (gh, gw)
        self.spectrum = np.stack([np.stack([sxx, sxy], -1), np.stack([sxy, syy], -1)], -2) * scale  # (gh, gw, 2, 2)
        self.sub_spectrum = [
            np.stack([np.stack([a, b], -1), np.stack([b, d], -1)], -2) * scale for a, b, d in sub_spec
        ]  # per level (n, n, 2, 2)
        self.root = torch.from_numpy(_psd_root(*self._components(self.spectrum))).to(torch.complex64)
        self.sub_root = [
            torch.from_numpy(_psd_root(*self._components(s))).to(torch.complex64) for s in self.sub_spectrum
        ]
        # e^{-2πi f·x} on the image rows / columns for each level
        ys, xs = np.arange(height), np.arange(width)
        self.sub_basis = [
            (
                torch.from_numpy(np.exp(-2j * np.pi * np.outer(ys, fyl))).to(torch.complex64),
                torch.from_numpy(np.exp(-2j * np.pi * np.outer(fxl, xs))).to(torch.complex64),
            )
            for fyl, fxl in self.sub_freqs
        ]

    @staticmethod
    def _components(spec: np.ndarray):
        return spec[..., 0, 0], spec[..., 0, 1], spec[..., 1, 1]

    def implied_covariance(self) -> np.ndarray:
        """Covariance tensor (gh, gw, 2, 2) of the generated fields versus pixel offset (torus order:
        offsets beyond half the period stand for the negative ones)."""
        gh, gw = self.grid
        cov = np.fft.ifft2(self.spectrum, axes=(0, 1)).real * (gh * gw)
        dy, dx = torus_offsets(gh, 1.0), torus_offsets(gw, 1.0)
        for (fyl, fxl), spec in zip(self.sub_freqs, self.sub_spectrum):
            ey, ex = np.exp(2j * np.pi * np.outer(dy, fyl)), np.exp(2j * np.pi * np.outer(fxl, dx))
            for a in range(2):
                for b in range(2):
                    cov[..., a, b] += (ey @ spec[..., a, b] @ ex).real
        return cov

    def sample(self, count: int, generator: torch.Generator | None = None, device="cpu") -> torch.Tensor:
        """(count, 2, H, W) float32 unit-variance fields; real and imaginary parts give two samples."""
        gh, gw = self.grid
        pairs = (count + 1) // 2
        gen_device = generator.device if generator is not None else torch.device("cpu")
        noise = torch.randn((pairs, gh, gw, 2, 2), generator=generator, device=gen_device).to(device)
        xi = torch.complex(noise[..., 0], noise[..., 1])
        if self.root.device != xi.device:
            self.root = self.root.to(xi.device)
            self.sub_root = [r.to(xi.device) for r in self.sub_root]
            self.sub_basis = [(ey.to(xi.device), ex.to(xi.device)) for ey, ex in self.sub_basis]
        # einsum returns a permuted view; torch.fft.fft2 on it aborted the process (SIGABRT, "malloc(): invalid
        # size") for 2-5 px high images: every FFT input in d2turb.sim is made contiguous first
        spec = torch.einsum("hwab,phwb->pahw", self.root, xi).contiguous()
        field = torch.fft.fft2(spec)[..., : self.height, : self.width]
        for root, (ey, ex) in zip(self.sub_root, self.sub_basis):
            n = root.shape[0]
            noise = torch.randn((pairs, n, n, 2, 2), generator=generator, device=gen_device).to(device)
            amp = torch.einsum("ijab,pijb->paij", root, torch.complex(noise[..., 0], noise[..., 1]))
            field = field + ey @ amp @ ex
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
        field = torch.fft.fft2((self.root * xi).contiguous())[..., : self.height, : self.width]
        return torch.cat([field.real, field.imag], 0)[:count].float()


class PlaneWaveGrid:
    """Σ_m a_m·e^{2πi f_m·x} on the H×W pixel grid for arbitrary (non-grid) frequencies f_m in cycles/px:
    a type-1 non-uniform FFT by Gaussian gridding (Greengard & Lee, SIAM Rev. 46, 2004). Each plane wave is
    spread with a Gaussian over ``2·half_width`` points per axis of a frequency grid ``oversample``× finer
    than the image's, one inverse FFT follows, and the Gaussian's transform is divided out. Frequencies act
    modulo 1 (sampling at integer pixels aliases them exactly like point sampling). Relative error about
    1e-5 at half-width 6. The plan (indices and weights) depends only on the frequencies, so a set of
    plane waves whose amplitudes change from frame to frame is planned once.
    """

    def __init__(self, height: int, width: int, half_width: int = 6, oversample: float = 2.0):
        self.height, self.width, self.w = height, width, half_width
        self.axes = []
        for n in (height, width):
            m = fast_size(max(math.ceil(oversample * n), n + 2 * half_width))
            tau = half_width / (4 * math.pi * m**1.5 * math.sqrt(m - n))  # truncation = aliasing error
            centre = n // 2
            xp = np.arange(n) - centre
            deconv = 1.0 / (math.sqrt(4 * math.pi * tau) * np.exp(-4 * math.pi**2 * tau * xp**2))
            self.axes.append(dict(m=m, tau=tau, centre=centre, rows=torch.from_numpy(xp % m), deconv=deconv))
        self.grid = (self.axes[0]["m"], self.axes[1]["m"])

    def _axis(self, f: torch.Tensor, ax: dict):
        """Grid indices (…, 2w) and Gaussian weights (…, 2w) of frequencies f (…) along one axis."""
        m, tau = ax["m"], ax["tau"]
        u = torch.remainder(f, 1.0) * m
        base = torch.floor(u).long()
        j = torch.arange(-self.w + 1, self.w + 1, device=f.device)
        idx = base[..., None] + j
        dist = (idx.to(f.dtype) - u[..., None]) / m
        return torch.remainder(idx, m), torch.exp(-(dist**2) / (4 * tau))

    def plan(self, freqs: torch.Tensor):
        """freqs (B, M, 2) float64, (f_y, f_x) → plan for ``__call__``."""
        b, n_modes, _ = freqs.shape
        if self.height * self.width <= (2 * self.w) ** 2:  # tiny frames: direct sums are cheaper
            ys = torch.arange(self.height, dtype=freqs.dtype, device=freqs.device)
            xs = torch.arange(self.width, dtype=freqs.dtype, device=freqs.device)
            ey = torch.polar(torch.ones_like(freqs[..., :1]), 2 * math.pi * freqs[..., :1] * ys)
            ex = torch.polar(torch.ones_like(freqs[..., 1:]), 2 * math.pi * freqs[..., 1:] * xs)
            return dict(direct=(ey.to(torch.complex64), ex.to(torch.complex64)))
        iy, wy = self._axis(freqs[..., 0], self.axes[0])
        ix, wx = self._axis(freqs[..., 1], self.axes[1])
        gh, gw = self.grid
        flat = (iy[..., :, None] * gw + ix[..., None, :]).reshape(b, -1)
        flat = flat + torch.arange(b, device=freqs.device)[:, None] * (gh * gw)
        weights = (wy[..., :, None] * wx[..., None, :]).reshape(b, n_modes, -1).float()
        centre = torch.tensor([self.axes[0]["centre"], self.axes[1]["centre"]], dtype=freqs.dtype, device=freqs.device)
        shift = torch.polar(torch.ones_like(freqs[..., 0]), 2 * math.pi * (freqs @ centre)).to(torch.complex64)
        deconv = np.outer(self.axes[0]["deconv"], self.axes[1]["deconv"])
        return dict(
            index=flat.reshape(-1),
            weights=weights,
            shift=shift,
            deconv=torch.from_numpy(deconv).float().to(freqs.device),
            rows=self.axes[0]["rows"].to(freqs.device),
            cols=self.axes[1]["rows"].to(freqs.device),
            batch=b,
        )

    def __call__(self, plan: dict, amps: torch.Tensor) -> torch.Tensor:
        """amps (B, M) complex → (B, H, W) complex64."""
        if "direct" in plan:
            ey, ex = plan["direct"]
            return (amps.to(torch.complex64)[..., None] * ey).transpose(-1, -2) @ ex
        gh, gw = self.grid
        vals = (amps.to(torch.complex64) * plan["shift"])[..., None] * plan["weights"]
        grid = torch.zeros(plan["batch"] * gh * gw, dtype=torch.complex64, device=amps.device)
        grid.index_add_(0, plan["index"], vals.reshape(-1))
        field = torch.fft.ifft2(grid.view(plan["batch"], gh, gw))  # a fresh 1-D buffer: contiguous
        return field[:, plan["rows"]][:, :, plan["cols"]] * plan["deconv"]


# ---- the theory that turbulence measurement inverts (d2turb.clip.strength, docs/measure.md) ------------------------
TILT_VARIANCE_COEF = 0.1816  # Z-tilt variance per axis in (λ/D)² (D/r0)^(5/3) rad² (docs/physics.md §2)


def tilt_variance_px2(dr0, aperture_m: float, wavelength_m: float, ifov_rad: float):
    """Z-tilt variance per axis in px²: 0.1816 (λ/D)² (D/r0)^(5/3) / ifov² (docs/physics.md §2)."""
    return TILT_VARIANCE_COEF * (wavelength_m / (aperture_m * ifov_rad)) ** 2 * np.asarray(dr0, np.float64) ** (5 / 3)


def dr0_from_tilt_variance(var_px2, aperture_m: float, wavelength_m: float, ifov_rad: float):
    """Inverse of :func:`tilt_variance_px2`: D/r0 = (σ²·ifov² / (0.1816 (λ/D)²))^(3/5)."""
    unit = TILT_VARIANCE_COEF * (wavelength_m / (aperture_m * ifov_rad)) ** 2
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
