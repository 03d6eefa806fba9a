"""Full-reference image metrics: functional ``psnr``/``ssim`` and torchmetrics-style accumulators.

Images are float tensors (B, C, H, W) (or one image (C, H, W)) in [0, 1]. The accumulators
(``PSNR``, ``SSIM``, ``LPIPSMetric``) average per-image values; under ``torch.distributed`` their
sums and counts are all-reduced in ``compute()``, so every rank gets the global mean.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from d2turb.errors import D2TurbError
from d2turb.eval.lpips import LPIPS
from d2turb.io import check_image_tensor

K1, K2 = 0.01, 0.03  # Wang et al. 2004 stabilising constants
MAX_PSNR_DB = 100.0  # identical images: PSNR is capped here instead of +inf, so means stay finite


def _pair(pred: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    if pred.ndim == 3:
        pred = pred[None]
    if target.ndim == 3:
        target = target[None]
    check_image_tensor(pred, "pred")
    check_image_tensor(target, "target")
    if pred.shape != target.shape:
        raise D2TurbError(f"pred and target shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}")
    return pred, target


def psnr(pred: torch.Tensor, target: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """Per-image PSNR in dB, shape (B,) (capped at 100 dB for identical images)."""
    pred, target = _pair(pred, target)
    mse = (pred.double() - target.double()).pow(2).flatten(1).mean(1)
    floor = data_range**2 * 10 ** (-MAX_PSNR_DB / 10)
    return 10 * torch.log10(data_range**2 / mse.clamp_min(floor))


def end_point_error(flow_px: torch.Tensor, target_px: torch.Tensor | None = None) -> torch.Tensor:
    """Flow end-point error: the mean over pixels of ‖flow − target‖₂ in pixels (``target`` None: zero flow).

    Shape:
        flow_px, target_px: (..., 2, H, W) → (...): a scalar for one flow, (B,) for a batch.
    """
    diff = flow_px if target_px is None else flow_px - target_px
    return diff.pow(2).sum(-3).sqrt().flatten(-2).mean(-1)


def _gaussian_kernel1d(sigma: float, truncate: float = 3.5) -> torch.Tensor:
    """The 1-D kernel of ``scipy.ndimage.gaussian_filter`` (radius = int(truncate * sigma + 0.5))."""
    radius = int(truncate * sigma + 0.5)
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def _filter_valid(x: torch.Tensor, k1d: torch.Tensor) -> torch.Tensor:
    """Separable depthwise filtering without padding (the 'valid' part skimage keeps after cropping)."""
    c = x.shape[1]
    k = k1d.to(x)
    x = F.conv2d(x, k.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    return F.conv2d(x, k.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)


def ssim(
    pred: torch.Tensor,
    target: torch.Tensor,
    data_range: float = 1.0,
    gaussian: bool = True,
    sigma: float = 1.5,
    win_size: int = 7,
) -> torch.Tensor:
    """Per-image mean SSIM (Wang et al. 2004), shape (B,), averaged over channels and pixels.

    ``gaussian=True`` (default) equals ``skimage.metrics.structural_similarity(..., channel_axis=-1,
    data_range=1.0, gaussian_weights=True, sigma=1.5, use_sample_covariance=False)``;
    ``gaussian=False`` equals skimage's default (``win_size``x``win_size`` uniform window, sample covariance).
    Like skimage, the mean is taken over pixels whose window lies inside the image.
    """
    pred, target = _pair(pred, target)
    x, y = pred, target  # float32 in, float32 filtering (fast, ~1e-6 from float64); float64 in, float64
    if gaussian:
        k1d, cov_norm = _gaussian_kernel1d(sigma), 1.0
    else:
        if win_size < 3 or win_size % 2 == 0:
            raise D2TurbError(f"ssim: win_size must be odd and >= 3, got {win_size}")
        k1d = torch.full((win_size,), 1.0 / win_size, dtype=torch.float64)
        cov_norm = win_size**2 / (win_size**2 - 1)  # sample covariance
    if min(x.shape[-2:]) < len(k1d):
        raise D2TurbError(f"ssim: images of {x.shape[-1]}x{x.shape[-2]} are smaller than the {len(k1d)}-pixel window")
    stats = _filter_valid(torch.cat([x, y, x * x, y * y, x * y], dim=1), k1d).chunk(5, dim=1)
    mx, my, mxx, myy, mxy = stats
    vx, vy, cxy = cov_norm * (mxx - mx * mx), cov_norm * (myy - my * my), cov_norm * (mxy - mx * my)
    c1, c2 = (K1 * data_range) ** 2, (K2 * data_range) ** 2
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))  # Eq. (13) of Wang et al.
    return s.flatten(1).double().mean(1)


class MeanMetric:
    """Running mean of per-image values; DDP-safe (sums and counts are all-reduced in ``compute``)."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.total = torch.zeros((), dtype=torch.float64)
        self.count = torch.zeros((), dtype=torch.float64)

    def per_image(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    @torch.no_grad()
    def update(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Add a batch; returns its per-image values."""
        values = self.per_image(pred, target).detach().double().cpu()
        self.total += values.sum()
        self.count += values.numel()
        return values

    def compute(self) -> float:
        """Mean over every image seen (on all ranks when torch.distributed is initialised)."""
        sums = torch.stack([self.total, self.count])
        dist = torch.distributed
        if dist.is_available() and dist.is_initialized():
            backend_device = "cuda" if dist.get_backend() == "nccl" else "cpu"
            sums = sums.to(backend_device)
            dist.all_reduce(sums, op=dist.ReduceOp.SUM)
            sums = sums.cpu()
        total, count = sums.tolist()
        return total / count if count else math.nan


class PSNR(MeanMetric):
    def __init__(self, data_range: float = 1.0) -> None:
        self.data_range = data_range
        super().__init__()

    def per_image(self, pred, target):
        return psnr(pred, target, self.data_range)


class SSIM(MeanMetric):
    def __init__(self, data_range: float = 1.0, gaussian: bool = True, sigma: float = 1.5, win_size: int = 7) -> None:
        self.kwargs = dict(data_range=data_range, gaussian=gaussian, sigma=sigma, win_size=win_size)
        super().__init__()

    def per_image(self, pred, target):
        return ssim(pred, target, **self.kwargs)


class LPIPSMetric(MeanMetric):
    """Mean LPIPS; ``model`` is a ``d2turb.eval.lpips.LPIPS`` (or built from its keyword arguments)."""

    def __init__(self, model=None, **lpips_kwargs) -> None:
        if model is None:
            model = LPIPS(**lpips_kwargs)
        self.model = model.eval()
        super().__init__()

    def per_image(self, pred, target):
        pred, target = _pair(pred, target)
        device = next(self.model.parameters()).device
        return self.model(pred.to(device), target.to(device))
