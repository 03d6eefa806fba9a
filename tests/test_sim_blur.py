"""PSF and blur kernels against plain reference algorithms: numpy FFT of the padded pupil, direct convolution."""

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from d2turb.sim import Optics
from d2turb.sim.psf import PupilPSF, blur_with_basis
from d2turb.sim.zernike import zernike


def _fft_psfs(coeffs, wl, ref_wl, d, ifov, modes, half, min_size=64):
    """|FFT(P·e^{iφ})|² on the nf = q·n_out grid (numpy), centred, binned q×q around the zero frequency, cropped."""
    q = max(1, math.ceil(2 * d * ifov / wl - 1e-9))
    q += 1 - q % 2
    n_out = max(min_size, 2 * math.ceil(12 * wl / (d * ifov)))
    nf, diam = q * n_out, d * n_out * ifov / wl
    size = int(math.ceil(diam)) + 2
    c = np.arange(size) - (size - 1) / 2
    yy, xx = np.meshgrid(c, c, indexing="ij")
    rho, theta = np.hypot(xx, yy) / (diam / 2), np.arctan2(yy, xx)
    inside = rho <= 1
    z = np.stack([zernike(j, rho, theta) for j in modes]) * (ref_wl / wl)
    out = []
    for a in coeffs:
        field = np.zeros((nf, nf), complex)
        field[:size, :size] = np.where(inside, np.exp(1j * np.tensordot(a, z, 1)), 0)
        psf = np.fft.fftshift(np.abs(np.fft.fft2(field)) ** 2)  # zero frequency at nf // 2
        m = (2 * half + 1) * q
        lo = nf // 2 - (m - 1) // 2
        psf = psf[lo : lo + m, lo : lo + m].reshape(2 * half + 1, q, 2 * half + 1, q).sum((1, 3))
        out.append(psf / psf.sum())
    return np.stack(out)


@pytest.mark.parametrize("wl", [525e-9, 450e-9])  # Nyquist (q = 1) and undersampled blue (q = 3)
def test_psfs_equal_the_fft_of_the_padded_pupil(wl):
    d, ref_wl, modes, half = 0.1, 525e-9, range(4, 16), 9
    ifov = ref_wl / (2 * d)
    coeffs = np.random.default_rng(0).normal(0, 1.2, size=(5, len(modes)))
    optics = Optics(d, (620e-9, ref_wl, 450e-9), ifov)  # the phase is given at the middle (reference) wavelength
    got = PupilPSF(optics, modes).psfs(torch.from_numpy(coeffs).float(), half)[optics.wavelengths.index(wl)]
    ref = _fft_psfs(coeffs, wl, ref_wl, d, ifov, modes, half)
    assert got.shape == ref.shape
    # float32 phases and products: absolute error ≈ 1e-7 on PSF values up to ≈ 0.2
    np.testing.assert_allclose(got.double().numpy(), ref, rtol=0, atol=2e-6)


@pytest.mark.parametrize("batch,basis_channels", [(1, 1), (2, 3), (3, 1), (4, 1)])
def test_blur_equals_direct_convolution(batch, basis_channels):
    """out = Σ_k w_k·(P_k ∗ I) by FFT (images paired in complex FFTs) against F.conv2d on the reflect-padded image."""
    g = torch.Generator().manual_seed(batch)
    image = torch.rand(batch, 3, 23, 30, generator=g, dtype=torch.float64)
    basis = torch.rand(basis_channels, 4, 7, 7, generator=g, dtype=torch.float64)
    weights = torch.randn(batch, 3, 3, 23, 30, generator=g, dtype=torch.float64)
    got = blur_with_basis(image, basis, weights)
    padded = F.pad(image, (3, 3, 3, 3), mode="reflect")
    ref = torch.zeros_like(image)
    for ch in range(3):
        kernels = basis[ch if basis_channels > 1 else 0].flip(-1, -2)[:, None]  # conv2d correlates: flip
        conv = F.conv2d(padded[:, ch : ch + 1], kernels)  # (B, K+1, H, W)
        ref[:, ch] = conv[:, 0] + (conv[:, 1:] * weights[:, ch]).sum(1)
    torch.testing.assert_close(got, ref, rtol=0, atol=1e-10)
