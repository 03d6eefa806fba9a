"""Exact PSFs from Zernike phase by pupil FFT, PCA basis and spatially varying blur."""

from __future__ import annotations

import math
import threading

import numpy as np
import torch
import torch.nn.functional as F

from d2turb.sim.tilt import fast_size
from d2turb.sim.zernike import zernike


class PupilOptics:
    """PSFs |FFT(P·e^{iφ})|², sampled at the detector pixel (ifov), for one or more wavelengths.

    Phase is an optical path difference: coefficients given in radians at ``ref_wavelength`` scale by
    λ_ref/λ_c per channel. The pupil spans D·n_out·ifov/λ_c FFT samples across, so one PSF sample is
    one pixel; undersampled pixels (ifov > λ/(2D)) are computed on an odd q× finer grid and binned.
    """

    def __init__(
        self,
        wavelengths,
        ref_wavelength: float,
        aperture_m: float,
        ifov_rad: float,
        modes: range,
        device="cpu",
        min_size: int = 64,
    ):
        self.modes, self.device = list(modes), torch.device(device)
        self.channels = []
        for wl in wavelengths:
            q = max(1, math.ceil(2 * aperture_m * ifov_rad / wl - 1e-9))
            q += 1 - q % 2  # odd, so a bin is centred on the zero-frequency sample
            n_out = max(min_size, 2 * math.ceil(12 * wl / (aperture_m * ifov_rad)))  # >= 24 pupil samples across
            nf = q * n_out
            diam = aperture_m * n_out * ifov_rad / wl  # pupil diameter in FFT samples
            size = int(math.ceil(diam)) + 2
            c = np.arange(size) - (size - 1) / 2
            yy, xx = np.meshgrid(c, c, indexing="ij")
            rho, theta = np.hypot(xx, yy) / (diam / 2), np.arctan2(yy, xx)
            inside = rho <= 1.0
            zern = np.stack([zernike(j, rho[inside], theta[inside]) for j in self.modes]) * (ref_wavelength / wl)
            rows, cols = np.nonzero(inside)
            self.channels.append(
                dict(
                    q=q,
                    n_out=n_out,
                    nf=nf,
                    zern=torch.from_numpy(zern).float().to(self.device),
                    index=torch.from_numpy(rows * nf + cols).to(self.device),
                )
            )
        self.max_half_window = min(ch["n_out"] for ch in self.channels) // 2 - 1

    def psfs(self, coeffs: torch.Tensor, half_window: int) -> torch.Tensor:
        """coeffs (N, len(modes)) in rad at λ_ref → PSFs (channels, N, w, w), w = 2·half_window+1, each summing to 1."""
        h = min(int(half_window), self.max_half_window)
        coeffs = coeffs.to(self.device, torch.float32)
        if coeffs.shape[0] > 2048:  # bound memory: the FFT work arrays are N × nf² complex
            return torch.cat([self.psfs(c, h) for c in coeffs.split(2048)], dim=1)
        out = []
        for ch in self.channels:
            n, nf, q, n_out = coeffs.shape[0], ch["nf"], ch["q"], ch["n_out"]
            phase = coeffs @ ch["zern"]
            field = torch.zeros(n, nf * nf, dtype=torch.complex64, device=self.device)
            field[:, ch["index"]] = torch.polar(torch.ones_like(phase), phase)
            psf = torch.fft.fft2(field.view(n, nf, nf)).abs().square()
            psf = torch.fft.fftshift(psf, dim=(-2, -1))
            if q > 1:
                psf = torch.roll(psf, shifts=((q - 1) // 2, (q - 1) // 2), dims=(-2, -1))
                psf = F.avg_pool2d(psf[:, None], q)[:, 0]
            c = n_out // 2
            psf = psf[:, c - h : c + h + 1, c - h : c + h + 1]
            out.append(psf / psf.sum(dim=(-2, -1), keepdim=True))
        return torch.stack(out)


_THREADS_LOCK = threading.Lock()


def _small_eigh(mat: torch.Tensor):
    """eigh of a small matrix on one thread: multi-threaded LAPACK on a busy CPU takes 10× longer and
    stalls for seconds (384×384 on 2 shared cores: 0.08 s on one thread, 0.75 s median / 7 s worst on two).

    torch's thread count is process-wide, so it is lowered only for this call and restored in ``finally``;
    the lock keeps two threads from saving and restoring each other's value.
    """
    if mat.device.type != "cpu":
        return torch.linalg.eigh(mat)
    with _THREADS_LOCK:
        threads = torch.get_num_threads()
        if threads == 1:
            return torch.linalg.eigh(mat)
        torch.set_num_threads(1)
        try:
            return torch.linalg.eigh(mat)
        finally:
            torch.set_num_threads(threads)


def pca_basis(psfs: torch.Tensor, max_components: int = 10, explained: float = 0.99, max_fit: int = 384):
    """PSFs (N, w, w) → basis (K+1, w, w) [mean, components summing to 0] and weights (N, K).

    The principal components are fitted on at most ``max_fit`` evenly strided PSFs (eigh of their Gram
    matrix), then every PSF is projected on them.
    """
    n, w, _ = psfs.shape
    x = psfs.reshape(n, -1).double()
    mean = x.mean(0)
    y = x - mean
    fit = y[:: max(1, math.ceil(n / max_fit))]
    lam, u = _small_eigh(fit @ fit.T)
    lam, u = lam.flip(0).clamp_min(0), u.flip(1)
    total = lam.sum()
    if total <= 1e-12 * float((mean * mean).sum()) * fit.shape[0]:
        k = 0
    else:
        k = (
            int(
                torch.searchsorted(
                    torch.cumsum(lam, 0) / total, torch.tensor(explained, dtype=lam.dtype, device=lam.device)
                ).item()
            )
            + 1
        )
        k = min(k, max_components, fit.shape[0])
    comps = (fit.T @ u[:, :k]) / lam[:k].sqrt().clamp_min(1e-30)
    comps = comps - comps.mean(0, keepdim=True)  # exactly zero-sum: a flat image stays flat
    weights = y @ comps  # projection (columns orthonormal up to the zero-sum correction)
    basis = torch.cat([mean[None], comps.T]).reshape(k + 1, w, w)
    return basis.float(), weights.float()


def blur_with_basis(image: torch.Tensor, basis: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Spatially varying blur in gather form: out(x) = Σ_k w_k(x)·(P_k ∗ I)(x), w_0 ≡ 1.

    image (B, C, H, W); basis (C|1, K+1, w, w); weights (B, C|1, K, H, W). Reflect padding, FFT convolution.
    """
    b, c, hgt, wid = image.shape
    half = basis.shape[-1] // 2
    mode = "reflect" if half < min(hgt, wid) else "replicate"
    padded = F.pad(image, (half, half, half, half), mode=mode) if half else image
    hp, wp = fast_size(padded.shape[-2]), fast_size(padded.shape[-1])  # zero-extended: no wrap into the crop
    img_f = torch.fft.rfft2(padded, s=(hp, wp))
    kern = torch.zeros(basis.shape[0], basis.shape[1], hp, wp, dtype=image.dtype, device=image.device)
    kern[..., : 2 * half + 1, : 2 * half + 1] = basis.to(image)
    kern_f = torch.fft.rfft2(torch.roll(kern, shifts=(-half, -half), dims=(-2, -1)))
    out = None
    for k in range(basis.shape[1]):
        conv = torch.fft.irfft2(img_f * kern_f[:, k], s=(hp, wp))[..., half : half + hgt, half : half + wid]
        term = conv if k == 0 else conv * weights[:, :, k - 1]
        out = term if out is None else out + term
    return out
