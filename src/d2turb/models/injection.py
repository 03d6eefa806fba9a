"""How the rectifier's shallow embedding F_shallow receives the backbone's F_guide (paper Sec. 3.2, Table ablation).

Every variant maps (F_shallow (B,C,H,W), F_guide (B,G,H,W)) -> F_fused (B,C,H,W):

* ``"aspi"`` — the authors' Adaptive Structural Prior Injection (Eq. 10), the paper configuration;
* ``"aspi_cosine"`` — our earlier variant: LayerNorm inputs, heads, L2-normalised q/k with a learned temperature
  (logits independent of the image size), output projection, per-channel γ (see docs/models.md);
* ``"concat"`` — concatenate, 1×1 conv (ablation);
* ``"none"`` — pure cascade (ablation).
"""

from __future__ import annotations

import math
from contextlib import nullcontext

import torch
from torch import nn

from d2turb.errors import D2TurbError
from d2turb.models.common import ChannelLayerNorm, transposed_attention


def channel_attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, return_attn: bool = False):
    """Softmax(Q Kᵀ / √(H·W)) V across channels, computed in float32.

    Each channel is one token whose embedding is its H·W pixels; this is ``scaled_dot_product_attention`` over
    (B, C, H·W) with one head, so the logits scale with the image size (no normalisation of q and k).

    Args:
        q: (B, C, H, W) queries; k, v: (B, C, H, W) keys and values.
        return_attn: also return the (B, C, C) attention matrix.

    Returns:
        (B, C, H, W) in the dtype of ``v`` (and the attention matrix when asked).
    """
    b, c, h, w = q.shape
    device = q.device.type
    autocast = torch.amp.is_autocast_available(device) and torch.is_autocast_enabled(device)
    no_autocast = torch.autocast(device, enabled=False) if autocast else nullcontext()
    with no_autocast:  # sums over all pixels: keep them in float32 under autocast too
        qf, kf, vf = (t.reshape(b, t.shape[1], h * w).float() for t in (q, k, v))
        attn = (qf @ kf.transpose(1, 2) / math.sqrt(h * w)).softmax(dim=-1)
        out = (attn @ vf).reshape(b, -1, h, w).to(v.dtype)
    return (out, attn) if return_attn else out


class NoInjection(nn.Module):
    """Pure cascade: the rectifier sees only Î_tilt."""

    def __init__(self, channels: int, guide_channels: int):
        super().__init__()

    def forward(self, shallow, guide):
        return shallow


class ConcatInjection(nn.Module):
    """Simple concat: F_fused = Conv1×1([F_shallow, F_guide])."""

    def __init__(self, channels: int, guide_channels: int):
        super().__init__()
        self.fuse = nn.Conv2d(channels + guide_channels, channels, 1)

    def forward(self, shallow, guide):
        return self.fuse(torch.cat([shallow, guide.to(shallow.dtype)], 1))


class ASPI(nn.Module):
    """The authors' ASPI, Eq. 10: F_fused = F_shallow + γ · Softmax(Q Kᵀ / √(H·W)) V.

    Q = 1×1 conv of F_shallow (C→C), K and V = 1×1 convs of F_guide (G→C), no biases, no normalisation; one head of
    channel attention (:func:`channel_attention`); no output projection; γ is one scalar initialised to 0, so
    F_fused = F_shallow exactly at initialisation.

    Shape: shallow (B, C, H, W), guide (B, G, H, W) -> (B, C, H, W).
    """

    def __init__(self, channels: int, guide_channels: int):
        super().__init__()
        self.gamma = nn.Parameter(torch.zeros(1))
        self.query = nn.Conv2d(channels, channels, 1, bias=False)
        self.key = nn.Conv2d(guide_channels, channels, 1, bias=False)
        self.value = nn.Conv2d(guide_channels, channels, 1, bias=False)

    def attend(self, shallow, guide, return_attn: bool = False):
        """Softmax(QKᵀ/√(HW))V (before γ); optionally the (B, C, C) attention matrix."""
        guide = guide.to(shallow.dtype)
        return channel_attention(self.query(shallow), self.key(guide), self.value(guide), return_attn)

    def forward(self, shallow, guide):
        return shallow + self.gamma.to(shallow.dtype) * self.attend(shallow, guide)  # Eq. 10


class CosineASPI(nn.Module):
    """Variant ``"aspi_cosine"`` of Eq. 10: F_fused = F_shallow + γ · W_o Softmax(Q̂ K̂ᵀ · τ) V.

    Q = W_q LN(F_shallow), K, V = W_k, W_v LN(F_guide); ``heads`` heads of channel attention in which Q and K are
    L2-normalised over pixels, so each logit is a cosine similarity in [-1, 1] scaled by a learned per-head
    temperature τ: the softmax has the same sharpness on 256² crops and full-size images (the authors' 1/√(H·W)
    scaling does not; see docs/models.md). γ (per channel) starts at ``gain_init`` = 1e-2, so the projections are
    trained from the first step on which the flow head has moved.
    """

    def __init__(self, channels: int, guide_channels: int, heads: int = 4, gain_init: float = 1e-2):
        super().__init__()
        if channels % heads:
            raise ValueError(f"aspi_cosine: channels ({channels}) must be divisible by heads ({heads})")
        self.heads = heads
        self.norm_q = ChannelLayerNorm(channels)
        self.norm_kv = ChannelLayerNorm(guide_channels)
        self.to_q = nn.Conv2d(channels, channels, 1, bias=False)
        self.to_kv = nn.Conv2d(guide_channels, 2 * channels, 1, bias=False)
        self.temperature = nn.Parameter(torch.ones(heads, 1, 1))
        self.project_out = nn.Conv2d(channels, channels, 1, bias=False)
        self.gain = nn.Parameter(torch.full((1, channels, 1, 1), float(gain_init)))

    def attend(self, shallow, guide, return_attn: bool = False):
        """Softmax(Q̂K̂ᵀτ)V after the output projection (before the gain); optionally the attention matrices."""
        q = self.to_q(self.norm_q(shallow))
        k, v = self.to_kv(self.norm_kv(guide.to(shallow.dtype))).chunk(2, dim=1)
        out, attn = transposed_attention(q, k, v, self.heads, self.temperature, return_attn=True)
        out = self.project_out(out)
        return (out, attn) if return_attn else out

    def forward(self, shallow, guide):
        return shallow + self.gain.to(shallow.dtype) * self.attend(shallow, guide)  # Eq. 10


INJECTIONS = {"none": NoInjection, "concat": ConcatInjection, "aspi": ASPI, "aspi_cosine": CosineASPI}


def create_injection(name: str, channels: int, guide_channels: int, **cfg) -> nn.Module:
    if name not in INJECTIONS:
        raise D2TurbError(f"unknown injection {name!r}; available: {', '.join(INJECTIONS)}")
    return INJECTIONS[name](channels, guide_channels, **cfg)
