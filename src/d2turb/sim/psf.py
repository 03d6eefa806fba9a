"""Exact PSFs from Zernike phase by pupil FFT, PCA basis and spatially varying blur."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from d2turb.device import one_torch_thread
from d2turb.sim.fields import fast_size
from d2turb.sim.optics import Optics
from d2turb.sim.zernike import zernike


class PupilPSF:
    """PSFs |FFT(P·e^{iφ})|² of an :class:`~d2turb.sim.Optics`, sampled at its detector pixel (ifov), one per
    wavelength of ``optics.wavelengths``.

    Phase is an optical path difference: coefficients given in radians at the reference wavelength scale by
    λ_ref/λ_c per channel. The pupil spans D·n_out·ifov/λ_c FFT samples across, so one PSF sample is
    one pixel; undersampled pixels (ifov > λ/(2D)) are computed on an odd q× finer grid and binned.

    Args:
        optics: the aperture D, the pixel ifov and the wavelengths (the phase refers to the reference one).
        modes: the Noll indices of the coefficients :meth:`psfs` takes.
        device: where the PSFs are computed.
        min_size: the PSF array's least size in pixels (the window :meth:`psfs` can return grows with it).
    """

    def __init__(self, optics: Optics, modes: range, device="cpu", min_size: int = 64):
        aperture_m, ifov_rad, ref_wavelength = optics.aperture_m, optics.ifov_rad, optics.reference_wavelength
        self.modes, self.device = list(modes), torch.device(device)
        self.channels = []
        for wl in optics.wavelengths:
            q = max(1, math.ceil(2 * aperture_m * ifov_rad / wl - 1e-9))
            q += 1 - q % 2  # odd, so a bin is centred on the zero-frequency sample
            n_out = max(min_size, 2 * math.ceil(12 * wl / (aperture_m * ifov_rad)))  # >= 24 pupil samples across
            diam = aperture_m * n_out * ifov_rad / wl  # pupil diameter in FFT samples
            size = int(math.ceil(diam)) + 2
            c = np.arange(size) - (size - 1) / 2
            yy, xx = np.meshgrid(c, c, indexing="ij")
            rho, theta = np.hypot(xx, yy) / (diam / 2), np.arctan2(yy, xx)
            inside = rho <= 1.0
            rows, cols = np.nonzero(inside)
            zern = np.stack([zernike(j, rho[inside], theta[inside]) for j in self.modes]) * (ref_wavelength / wl)
            # The DFT runs on the disk's bounding box: where the pupil sits in the zero-padded nf² grid only adds
            # a linear phase to its transform, which |.|² removes.
            rows, cols = rows - rows.min(), cols - cols.min()
            box = int(max(rows.max(), cols.max())) + 1
            zern_box = np.zeros((len(self.modes), box, 2, box))  # (mode, row, re|im, col), as psfs() reads it
            zern_box[:, rows, :, cols] = zern.T[:, :, None]
            amp = np.zeros((box, 2, box))
            amp[rows, :, cols] = 1.0
            phase_offset = np.zeros((box, 2, box))
            phase_offset[:, 1] = -math.pi / 2  # cos(φ − π/2) = sin φ: one cos gives both parts of e^{iφ}
            self.channels.append(
                dict(
                    q=q,
                    n_out=n_out,
                    nf=q * n_out,
                    box=box,
                    zern=torch.from_numpy(zern_box.reshape(len(self.modes), -1)).float().to(self.device),
                    amp=torch.from_numpy(amp.reshape(-1)).float().to(self.device),
                    offset=torch.from_numpy(phase_offset.reshape(-1)).float().to(self.device),
                )
            )
        self.max_half_window = min(ch["n_out"] for ch in self.channels) // 2 - 1
        self._dft: dict = {}

    def _dft_matrix(self, ch: dict, half: int) -> torch.Tensor:
        """Real form W (2·box, 2m) of the DFT of a box-long signal at the m = 2·half+1 frequencies −half..half of
        an nf-point FFT: [x_re | x_im] @ W = [X_re | X_im]."""
        key = (ch["nf"], ch["box"], half)
        if key not in self._dft:
            u = np.arange(-half, half + 1)[None, :]
            n = np.arange(ch["box"])[:, None]
            ang = 2 * np.pi * ((n * u) % ch["nf"]) / ch["nf"]
            cos, sin = np.cos(ang), -np.sin(ang)  # e^{-2πi·n·u/nf}
            w = np.block([[cos, sin], [-sin, cos]])
            self._dft[key] = torch.from_numpy(w).float().to(self.device)
        return self._dft[key]

    def psfs(self, coeffs: torch.Tensor, half_window: int) -> torch.Tensor:
        """coeffs (N, len(modes)) in rad at λ_ref → PSFs (channels, N, w, w), w = 2·half_window+1, each summing to 1."""
        h = min(int(half_window), self.max_half_window)
        coeffs = coeffs.to(self.device, torch.float32)
        n, w = coeffs.shape[0], 2 * h + 1
        out = torch.empty(len(self.channels), n, w, w, device=self.device)
        for ci, ch in enumerate(self.channels):
            q, box = ch["q"], ch["box"]
            m = w * q  # frequencies kept: the window, q samples per pixel
            dft = self._dft_matrix(ch, (m - 1) // 2)
            per_psf = 2 * box * box + 2 * box * m + 2 * m * m  # floats of work per PSF
            chunk = max(1, _chunk_floats(self.device) // per_psf)
            for a in range(0, n, chunk):
                c = coeffs[a : a + chunk]
                k = c.shape[0]
                field = torch.addmm(ch["offset"], c, ch["zern"]).cos_().mul_(ch["amp"])  # (k, box·2·box)
                rows_f = (field.view(k * box, 2 * box) @ dft).view(k, box, 2, m)  # FFT along x
                cols_f = rows_f.permute(0, 3, 2, 1).reshape(k * m, 2 * box) @ dft  # then along y
                cols_f = cols_f.view(k, m, 2, m)  # (k, x freq, re|im, y freq)
                psf = cols_f[:, :, 0].square().addcmul_(cols_f[:, :, 1], cols_f[:, :, 1]).transpose(1, 2)
                if q > 1:  # bin q×q samples; the bins are centred on multiples of q
                    psf = psf.reshape(k, w, q, w, q).sum(dim=(2, 4))
                torch.div(psf, psf.sum(dim=(-2, -1), keepdim=True), out=out[ci, a : a + k])
        return out


def _chunk_floats(device: torch.device) -> int:
    """Work-array floats per chunk of PSFs: on a CPU small enough to stay in cache (the matrices are tall and thin;
    2312 PSFs: 0.14–0.22 s at 2^19 with one or two threads on a lightly loaded 2-core machine), 256 MiB on a GPU.
    Fixed per device type, never from the thread count: the chunk changes the matrix products' rounding, and
    outputs must not depend on how many threads made them (make-dataset restarts are byte-identical)."""
    return 1 << 26 if device.type != "cpu" else 1 << 19


def pca_basis(psfs: torch.Tensor, max_components: int = 10, explained: float = 0.99, max_fit: int = 384):
    """PSFs (N, w, w) → basis (K+1, w, w) [mean, components summing to 0] and weights (N, K).

    The principal components are fitted on at most ``max_fit`` evenly strided PSFs (eigh of their Gram
    matrix), then every PSF is projected on them. On a CPU it runs on one thread, so the result does not
    depend on the thread count (:func:`d2turb.device.one_torch_thread`): MKL splits the Gram matrix's long inner
    dimension (w² up to ~10⁴) by thread count, and a make-dataset resumed on another count would not be
    byte-identical; a multi-threaded eigh of a small matrix also stalls on a busy CPU (384×384 on 2 shared cores:
    0.08 s on one thread, 0.75 s median / 7 s worst on two).
    """
    with one_torch_thread(psfs.device):
        return _pca_basis(psfs, max_components, explained, max_fit)


def _pca_basis(psfs: torch.Tensor, max_components: int, explained: float, max_fit: int):
    n, w, _ = psfs.shape
    x = psfs.reshape(n, -1)
    mean = x.mean(0).double()  # only the fitted PSFs are copied to float64
    fit = x[:: max(1, math.ceil(n / max_fit))].double() - mean
    lam, u = torch.linalg.eigh(fit @ fit.T)
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
    # projection (columns orthonormal up to the zero-sum correction), in float32: no float64 copy of all N PSFs
    weights = x @ comps.float() - (mean @ comps).float()
    basis = torch.cat([mean[None], comps.T]).reshape(k + 1, w, w)
    return basis.float(), weights.float()


def _full_spectrum(half_spec: torch.Tensor, width: int) -> torch.Tensor:
    """Full 2-D DFT (…, h, width) of real planes from their ``rfft2`` (…, h, width//2+1): X(−k) = X(k)*."""
    h, wh = half_spec.shape[-2], half_spec.shape[-1]
    rows = (-torch.arange(h, device=half_spec.device)) % h
    cols = width - torch.arange(wh, width, device=half_spec.device)
    rest = half_spec.index_select(-2, rows).index_select(-1, cols).conj()
    return torch.cat([half_spec, rest], -1)


def _cmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a·b for complex tensors, on one thread (CPU). torch's complex ``*`` rounds differently in its vectorised loop
    and its scalar tail, and where one ends depends on how the work is split over the threads: the same spectra
    multiplied on 1, 2 or 4 threads differed in the last bits. On one thread the split is always the same; this
    memory-bound product is also faster there on a busy machine (300² × 6 planes: 1.4 ms on one thread, 15 ms on
    two with the other core loaded)."""
    with one_torch_thread(a.device):
        return a * b


def blur_with_basis(image: torch.Tensor, basis: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Spatially varying blur in gather form: out(x) = Σ_k w_k(x)·(P_k ∗ I)(x), w_0 ≡ 1.

    image (B, C, H, W); basis (C|1, K+1, w, w); weights (B, C|1, K, H, W). Reflect padding, FFT convolution.
    Two images of a batch share one complex FFT: the kernels are real, so P ∗ (I_a + i·I_b) = P ∗ I_a +
    i·(P ∗ I_b), and one complex inverse FFT of a batch costs half as much as two real ones on a CPU (MKL,
    24 planes of 300²: 4.9 against 10.6 ms).
    """
    b, c, hgt, wid = image.shape
    half = basis.shape[-1] // 2
    mode = "reflect" if half < min(hgt, wid) else "replicate"
    padded = F.pad(image, (half, half, half, half), mode=mode) if half else image
    hp, wp = fast_size(padded.shape[-2]), fast_size(padded.shape[-1])  # zero-extended: no wrap into the crop
    kern = torch.zeros(basis.shape[0], basis.shape[1], hp, wp, dtype=image.dtype, device=image.device)
    kern[..., : 2 * half + 1, : 2 * half + 1] = basis.to(image)
    kern_f = torch.fft.rfft2(torch.roll(kern, shifts=(-half, -half), dims=(-2, -1)).contiguous())
    if b == 1:  # nothing to pair with
        img_f = torch.fft.rfft2(padded.contiguous(), s=(hp, wp))
        out = None
        for k in range(basis.shape[1]):
            conv = torch.fft.irfft2(_cmul(img_f, kern_f[:, k]), s=(hp, wp))[..., half : half + hgt, half : half + wid]
            out = conv.clone() if k == 0 else out.addcmul_(conv, weights[:, :, k - 1])
        return out
    na = (b + 1) // 2  # images 0..na-1 in the real parts, na..b-1 in the imaginary parts
    nb = b - na
    second = padded[na:] if nb == na else torch.cat([padded[na:], torch.zeros_like(padded[:1])])
    img_f = torch.fft.fft2(torch.complex(padded[:na], second).contiguous(), s=(hp, wp))
    kern_f = _full_spectrum(kern_f, wp)
    w_a, w_b = (weights[:na], weights[na:]) if weights.shape[0] > 1 else (weights, weights)
    out_a = out_b = None
    for k in range(basis.shape[1]):
        conv = torch.fft.ifft2(_cmul(img_f, kern_f[:, k]))[..., half : half + hgt, half : half + wid]
        if k == 0:
            out_a, out_b = conv.real.clone(), conv.imag[:nb].clone()
        else:
            out_a.addcmul_(conv.real, w_a[:, :, k - 1])
            out_b.addcmul_(conv.imag[:nb], w_b[:, :, k - 1])
    return torch.cat([out_a, out_b])
