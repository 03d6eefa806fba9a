"""Weight-free relative depth for outdoor long-range scenes (d̃ ∈ [0, 1], far = 1).

Methods (``estimate_depth_prior(image, method=...)``):
* ``vertical``: the top of the frame is farther (ground plane seen from a level camera).
* ``haze``: dark-channel prior (He et al., CVPR 2009): transmission t = 1 − ω·dark(I/A) and
  t = e^(−βd) ⇒ d ∝ −ln t, refined with the guided filter (He et al., ECCV 2010).
* ``cap``: colour-attenuation prior (Zhu et al., TIP 2015): d = θ0 + θ1·V + θ2·S, min-filtered and
  guided-filter refined.
* ``haze+vertical`` / ``cap+vertical``: equal-weight blend of the rank-normalised cue and the
  vertical prior.
The default (``DEFAULT_METHOD``) is the one with the best mean Spearman correlation against measured
KITTI depth (docs/depth.md).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from d2turb.errors import D2TurbError
from d2turb.ops.checks import check_shape

METHODS = ("vertical", "haze", "cap", "haze+vertical", "cap+vertical")
DEFAULT_METHOD = "cap+vertical"
CUE_WEIGHT = 0.1
WORK_SIZE = 512  # long side at which the haze cues are computed


def _window_sum(x: torch.Tensor, r: int, dim: int) -> torch.Tensor:
    """Sum over [i − r, i + r] along ``dim`` (clipped at the border) by a cumulative sum."""
    n = x.shape[dim]
    c = torch.cat((torch.zeros_like(x.narrow(dim, 0, 1)), x.cumsum(dim)), dim)
    idx = torch.arange(n, device=x.device)
    hi, lo = (idx + r + 1).clamp(max=n), (idx - r).clamp(min=0)
    return c.index_select(dim, hi) - c.index_select(dim, lo)


def box_filter(x: torch.Tensor, r: int) -> torch.Tensor:
    """Mean over the (2r+1)² window, windows clipped at the border (B, C, H, W); O(1) per pixel."""
    ones = torch.ones_like(x[:1, :1])
    count = _window_sum(_window_sum(ones, r, -2), r, -1)
    return _window_sum(_window_sum(x, r, -2), r, -1) / count


def guided_filter(guide: torch.Tensor, src: torch.Tensor, r: int, eps: float) -> torch.Tensor:
    """Grey-guide guided filter (He et al. 2010, Alg. 1): q = mean(a)·I + mean(b), a = cov(I,p)/(var(I)+ε)."""
    mean_i, mean_p = box_filter(guide, r), box_filter(src, r)
    cov_ip = box_filter(guide * src, r) - mean_i * mean_p
    var_i = box_filter(guide * guide, r) - mean_i * mean_i
    a = cov_ip / (var_i + eps)
    b = mean_p - a * mean_i
    return box_filter(a, r) * guide + box_filter(b, r)


def min_filter(x: torch.Tensor, r: int) -> torch.Tensor:
    """Minimum over the (2r+1)² window (separable; border replicated)."""
    k = 2 * r + 1
    x = -F.max_pool2d(F.pad(-x, (r, r, 0, 0), mode="replicate"), (1, k), stride=1)
    return -F.max_pool2d(F.pad(-x, (0, 0, r, r), mode="replicate"), (k, 1), stride=1)


def _minmax(x: torch.Tensor) -> torch.Tensor:
    lo = x.amin(dim=(-2, -1), keepdim=True)
    hi = x.amax(dim=(-2, -1), keepdim=True)
    return ((x - lo) / (hi - lo).clamp_min(1e-12)).clamp(0, 1)


def _rank_normalise(x: torch.Tensor) -> torch.Tensor:
    """Per-image ranks scaled to [0, 1] (makes cues with different distributions blendable)."""
    b, c, h, w = x.shape
    flat = x.reshape(b, -1)
    ranks = torch.empty_like(flat)
    order = flat.argsort(dim=1)
    ranks.scatter_(
        1, order, torch.linspace(0, 1, flat.shape[1], dtype=x.dtype, device=x.device).expand(b, -1).contiguous()
    )
    return ranks.reshape(b, c, h, w)


def vertical_prior(batch: int, height: int, width: int, device=None) -> torch.Tensor:
    """d̃ = 1 at the top row, 0 at the bottom row."""
    ramp = torch.linspace(1.0, 0.0, height, device=device)
    return ramp.view(1, 1, height, 1).expand(batch, 1, height, width).contiguous()


def _scales(h: int, w: int) -> tuple[int, int]:
    """Patch radius of the dark channel and guided-filter radius, scaled with the image size."""
    side = min(h, w)
    return max(1, round(side / 50)), max(2, round(side / 12))


def _grey(image: torch.Tensor) -> torch.Tensor:
    return 0.299 * image[:, 0:1] + 0.587 * image[:, 1:2] + 0.114 * image[:, 2:3]


def haze_depth(image: torch.Tensor, omega: float = 0.95, eps: float = 1e-3) -> torch.Tensor:
    """Dark-channel transmission → d ∝ −ln t (t = e^(−βd)), guided-filter refined; (B,1,H,W) in [0,1]."""
    b, _, h, w = image.shape
    r_patch, r_guide = _scales(h, w)
    dark = min_filter(image.amin(dim=1, keepdim=True), r_patch)
    # atmospheric light A: mean colour of the 0.1 % brightest dark-channel pixels
    n_top = max(1, h * w // 1000)
    idx = dark.reshape(b, -1).topk(n_top, dim=1).indices
    atm = torch.gather(image.reshape(b, 3, -1), 2, idx[:, None].expand(b, 3, n_top)).mean(dim=2).clamp_min(1e-3)
    normed = image / atm[:, :, None, None]
    t = 1.0 - omega * min_filter(normed.amin(dim=1, keepdim=True), r_patch)
    t = guided_filter(_grey(image), t, r_guide, eps).clamp(0.05, 1.0)
    return _minmax(-torch.log(t))


def cap_depth(image: torch.Tensor, eps: float = 1e-3) -> torch.Tensor:
    """Colour-attenuation prior d = θ0 + θ1·V + θ2·S (Zhu et al. 2015 coefficients), refined."""
    b, _, h, w = image.shape
    r_patch, r_guide = _scales(h, w)
    v = image.amax(dim=1, keepdim=True)
    s = (v - image.amin(dim=1, keepdim=True)) / v.clamp_min(1e-6)
    d = 0.121779 + 0.959710 * v - 0.780245 * s
    d = min_filter(d, r_patch)
    return _minmax(guided_filter(_grey(image), d, r_guide, eps))


def estimate_depth_prior(
    image: torch.Tensor, method: str = DEFAULT_METHOD, cue_weight: float = CUE_WEIGHT
) -> torch.Tensor:
    """Weight-free relative depth: image (3,H,W) → (1,H,W), or (B,3,H,W) → (B,1,H,W); [0,1], far = 1.

    ``cue_weight``: weight of the rank-normalised haze cue in the ``*+vertical`` blends.
    """
    if method not in METHODS:
        raise D2TurbError(f"depth prior method {method!r}: expected one of {', '.join(METHODS)}")
    check_shape(image, "[B] 3 H W", "estimate_depth_prior: RGB image")
    single = image.ndim == 3
    x = image[None] if single else image
    if not torch.isfinite(x).all():
        raise D2TurbError("estimate_depth_prior: image contains NaN or infinite values")
    x = x.float().clamp(0, 1)
    b, _, h, w = x.shape
    with torch.no_grad():
        vert = vertical_prior(b, h, w, x.device)
        if method == "vertical":
            out = vert
        else:
            small = x
            if max(h, w) > WORK_SIZE:  # the cues are smooth: estimate at ≤ WORK_SIZE px, upsample
                scale = WORK_SIZE / max(h, w)
                small = F.interpolate(x, size=(max(2, round(h * scale)), max(2, round(w * scale))), mode="area")
            cue = haze_depth(small) if method.startswith("haze") else cap_depth(small)
            if "+" in method:
                cue = _rank_normalise(cue)
            cue = (
                F.interpolate(cue, size=(h, w), mode="bilinear", align_corners=False)
                if cue.shape[-2:] != (h, w)
                else cue
            )
            out = cue if "+" not in method else _minmax(cue_weight * cue + (1 - cue_weight) * vert)
    return out[0] if single else out
