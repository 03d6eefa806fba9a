"""Small building blocks shared by the backbones and the rectifier, and the input check of every model."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from d2turb.errors import D2TurbError
from d2turb.ops.checks import check_shape


def check_input(image: torch.Tensor) -> None:
    """Refuse what no restoration model takes: anything but a floating (B, 3, H, W) batch at least 2 px a side."""
    check_shape(image, "B 3 H W", "model input", floating=True)
    if min(image.shape[-2:]) < 2:
        raise D2TurbError(f"model input is too small: {tuple(image.shape[-2:])}")


def pad_to_size(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Pad H and W at the bottom/right up to ``size`` (reflect; replicate when a pad is not smaller than the side)."""
    h, w = x.shape[-2:]
    ph, pw = size[0] - h, size[1] - w
    if ph < 0 or pw < 0:
        raise ValueError(f"cannot pad {(h, w)} to the smaller size {tuple(size)}")
    if ph or pw:
        mode = "reflect" if ph < h and pw < w else "replicate"
        x = F.pad(x, (0, pw, 0, ph), mode=mode)
    return x


def pad_to_multiple(x: torch.Tensor, multiple: int) -> tuple[torch.Tensor, tuple[int, int]]:
    """Pad H and W at the bottom/right up to a multiple (as :func:`pad_to_size`); returns (padded, original (H, W))."""
    h, w = x.shape[-2:]
    return pad_to_size(x, (h + (-h) % multiple, w + (-w) % multiple)), (h, w)


class ChannelLayerNorm(nn.Module):
    """LayerNorm over channels of a (B, C, H, W) map, computed in float32. ``bias=False`` = Restormer's BiasFree
    variant (x / sqrt(var + eps) * w, the mean is not subtracted).

    With bias, ``F.layer_norm`` runs on the channels-last view (one fused pass, faster than var + mean on a CPU:
    benchmarks/RESULTS.md) and the output keeps that memory layout.
    """

    def __init__(self, channels: int, bias: bool = True, eps: float = 1e-5):
        super().__init__()
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels)) if bias else None
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        xf = x.float()
        if self.bias is None:
            var = xf.var(dim=1, keepdim=True, unbiased=False)
            y = xf / torch.sqrt(var + self.eps) * self.weight[:, None, None]
        else:
            w, b = self.weight.float(), self.bias.float()  # float32 also when the module was cast to bf16
            y = F.layer_norm(xf.permute(0, 2, 3, 1), (x.shape[1],), w, b, self.eps)
            y = y.permute(0, 3, 1, 2)
        return y.to(x.dtype)


def transposed_attention(
    q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, heads: int, temperature: torch.Tensor, return_attn: bool = False
):
    """Attention across channels (Restormer MDTA): q, k, v (B, C, H, W); q and k are L2-normalised over pixels,
    so logits are cosine similarities scaled by a learned per-head temperature, independent of image size.
    Returns (B, C, H, W) and optionally the (B, heads, C/h, C/h) attention matrices."""
    b, c, h, w = q.shape
    q, k, v = (t.reshape(b, heads, t.shape[1] // heads, h * w) for t in (q, k, v))
    q = F.normalize(q.float(), dim=-1)
    k = F.normalize(k.float(), dim=-1)
    attn = (q @ k.transpose(-2, -1) * temperature.float()).softmax(dim=-1)
    out = (attn.to(v.dtype) @ v).reshape(b, -1, h, w)
    return (out, attn) if return_attn else out
