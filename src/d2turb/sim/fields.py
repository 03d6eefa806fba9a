"""Gaussian random fields for the simulator: tilt (2-vector) fields with the layers' exact tensor spectrum
(:class:`VectorFieldSampler`), scalar fields of given covariances (:class:`ScalarFieldSampler`), and sums of
plane waves at arbitrary frequencies (:class:`PlaneWaveGrid`, the frozen-flow sequences'); the correlations they
follow are :mod:`d2turb.sim.tilt`'s."""

from __future__ import annotations

import math

import numpy as np
import torch

from d2turb.sim.tilt import layer_tilt_spectrum


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


def _psd_root(sxx: np.ndarray, sxy: np.ndarray, syy: np.ndarray) -> np.ndarray:
    """Closed-form square root of PSD 2×2 matrices [[sxx, sxy], [sxy, syy]]: (A + √det·I)/√(tr + 2√det)."""
    sdet = np.sqrt(np.clip(sxx * syy - sxy * sxy, 0, None))
    norm = np.sqrt(np.clip(sxx + syy + 2 * sdet, 1e-300, None))
    return np.stack([np.stack([sxx + sdet, sxy], -1), np.stack([sxy, syy + sdet], -1)], -2) / norm[..., None, None]


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
