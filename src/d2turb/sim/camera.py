"""The camera after the air: functional ops on (..., C, H, W) tensors, kornia-style (no state, any batch shape).

Order of a camera (what ``make-dataset --profile field`` applies, d2turb.data.field): light arrives as linear
radiance → lens blur beyond diffraction (:func:`optics_blur`: defocus disk ⊗ Gaussian lens MTF) → exposure and
sensor noise in linear light (:func:`poisson_gaussian_noise`) → highlight clipping at saturation → tone curve
(:func:`linear_to_srgb`, IEC 61966-2-1) → in-camera sharpening (:func:`unsharp_mask`) on the encoded values →
resize → codec (d2turb.video_codec.encode_decode, JPEG).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

# IEC 61966-2-1:1999 (sRGB): the linear segment below the threshold, the 2.4-power segment above it
SRGB_A = 0.055
SRGB_GAMMA = 2.4
SRGB_SLOPE = 12.92
SRGB_LINEAR_MAX = 0.0031308  # linear value where the segments meet
SRGB_ENCODED_MAX = 0.04045  # encoded value where they meet (12.92 · 0.0031308 ≈ 0.04045)


def srgb_to_linear(encoded: torch.Tensor) -> torch.Tensor:
    """sRGB-encoded values → linear light (IEC 61966-2-1): v/12.92 below 0.04045, ((v + 0.055)/1.055)^2.4 above.

    Args:
        encoded: (..., C, H, W) in [0, 1] (values outside are extended: negatives linearly, above 1 by the power).
    Returns:
        linear values of the same shape and dtype.
    """
    x = encoded
    return torch.where(
        x <= SRGB_ENCODED_MAX, x / SRGB_SLOPE, ((x.clamp_min(SRGB_ENCODED_MAX) + SRGB_A) / (1 + SRGB_A)) ** SRGB_GAMMA
    )


def linear_to_srgb(linear: torch.Tensor) -> torch.Tensor:
    """Linear light → sRGB-encoded values (IEC 61966-2-1): 12.92·L below 0.0031308, 1.055·L^(1/2.4) − 0.055 above.

    Args:
        linear: (..., C, H, W), usually in [0, 1].
    Returns:
        encoded values of the same shape and dtype (not clipped).
    """
    x = linear
    return torch.where(
        x <= SRGB_LINEAR_MAX,
        x * SRGB_SLOPE,
        (1 + SRGB_A) * x.clamp_min(SRGB_LINEAR_MAX) ** (1 / SRGB_GAMMA) - SRGB_A,
    )


def poisson_gaussian_variance(linear: torch.Tensor, gain: float, read_sigma: float) -> torch.Tensor:
    """Variance of the Poisson–Gaussian sensor model at the clean linear value x: ``gain·x + read_sigma²``
    (Foi et al., IEEE TIP 2008: y = gain·P(x/gain) + N(0, read_sigma²); 1/gain photo-electrons at x = 1)."""
    return gain * linear.clamp_min(0) + read_sigma**2


def poisson_gaussian_noise(
    linear: torch.Tensor, gain: float, read_sigma: float, generator: torch.Generator | None = None
) -> torch.Tensor:
    """Sensor noise on linear values: ``gain·Poisson(x/gain) + N(0, read_sigma²)`` (shot noise of x/gain
    photo-electrons, read noise); the mean stays x, the variance is :func:`poisson_gaussian_variance`.

    Args:
        linear: (..., C, H, W) clean linear values ≥ 0 (negatives count as 0).
        gain: linear value of one photo-electron (> 0; 0 gives no shot noise).
        read_sigma: standard deviation of the read noise, in linear units.
        generator: torch generator (CPU) for reproducible draws.
    Returns:
        the noisy values, same shape, float32 (not clipped).
    """
    x = linear.float().clamp_min(0)
    if gain > 0:
        x = torch.poisson(x / gain, generator=generator) * gain
    if read_sigma > 0:
        x = x + read_sigma * torch.randn(x.shape, generator=generator, dtype=x.dtype)
    return x


def _filter2d(image: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    """Same-size 2-D convolution of every channel with a (k, k) kernel, borders reflected."""
    shape = image.shape
    x = image.reshape(-1, 1, *shape[-2:])
    r = kernel.shape[-1] // 2
    x = F.pad(x, (r, r, r, r), mode="reflect")
    return F.conv2d(x, kernel.to(x)[None, None]).reshape(shape)


def gaussian_kernel(sigma_px: float, radius: int | None = None) -> torch.Tensor:
    """Normalised (2r+1)² Gaussian kernel of standard deviation ``sigma_px`` (r = ceil(3σ) by default)."""
    r = max(1, math.ceil(3 * sigma_px)) if radius is None else radius
    t = torch.arange(-r, r + 1, dtype=torch.float64)
    g = torch.exp(-0.5 * (t / max(sigma_px, 1e-6)) ** 2)
    k = torch.outer(g, g)
    return (k / k.sum()).float()


def defocus_kernel(radius_px: float, supersample: int = 8) -> torch.Tensor:
    """Normalised uniform disk (geometric defocus) of radius ``radius_px``, its edge pixels weighted by their
    covered area (``supersample``² sub-pixels each); radius < 0.5 px gives the identity."""
    r = max(0, math.ceil(radius_px - 0.5))
    if radius_px < 0.5 or r == 0:
        return torch.ones(1, 1)
    s = supersample
    t = (torch.arange((2 * r + 1) * s, dtype=torch.float64) + 0.5) / s - (r + 0.5)
    inside = (t[:, None] ** 2 + t[None, :] ** 2 <= radius_px**2).double()
    k = inside.reshape(2 * r + 1, s, 2 * r + 1, s).mean((1, 3))
    return (k / k.sum()).float()


def optics_blur(linear: torch.Tensor, defocus_px: float, mtf_sigma_px: float) -> torch.Tensor:
    """The lens beyond diffraction on linear light: a defocus disk of radius ``defocus_px`` then a Gaussian of
    ``mtf_sigma_px`` (the lens MTF's fall-off: aberrations, the sensor's anti-aliasing filter). Shape kept."""
    x = linear
    if defocus_px >= 0.5:
        x = _filter2d(x, defocus_kernel(defocus_px))
    if mtf_sigma_px > 0:
        x = _filter2d(x, gaussian_kernel(mtf_sigma_px))
    return x


def unsharp_mask(image: torch.Tensor, amount: float, sigma_px: float) -> torch.Tensor:
    """In-camera sharpening: ``image + amount·(image − G_σ ∗ image)`` (not clipped). Shape kept."""
    if amount <= 0:
        return image
    return image + amount * (image - _filter2d(image, gaussian_kernel(sigma_px)))


def expose(linear: torch.Tensor, exposure: float, saturation: float = 1.0) -> torch.Tensor:
    """Exposure gain then highlight clipping at the sensor's saturation: ``clip(exposure·x, 0, saturation)``."""
    return (linear * exposure).clamp(0, saturation)
