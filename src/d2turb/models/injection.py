"""How the rectifier's shallow embedding F_shallow receives the backbone's F_guide (paper Sec. 3.2, Table ablation):
"none" (pure cascade), "concat" (concatenate, 1×1 conv) and "aspi" (Adaptive Structural Prior Injection, Eq. 10).
Every variant maps (F_shallow (B,C,H,W), F_guide (B,G,H,W)) -> F_fused (B,C,H,W)."""

from __future__ import annotations

import torch
from torch import nn

from d2turb.errors import D2TurbError
from d2turb.models.common import ChannelLayerNorm, transposed_attention


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
    """Eq. 10: F_fused = F_shallow + γ · Softmax(Q Kᵀ · τ) V with Q = W_q F_shallow, K = W_k F_guide, V = W_v F_guide.

    The attention runs across channels (transposed attention as in Restormer's MDTA): Q and K are L2-normalised
    over pixels, so each logit is a cosine similarity in [-1, 1] scaled by a learned per-head temperature τ (which
    replaces the fixed 1/√d). Its sharpness is therefore the same on 256² crops and full-size images, and the cost is
    linear in the number of pixels. γ (per channel) starts at ``gain_init`` = 1e-2: small, so F_fused ≈ F_shallow at
    init, but nonzero, so ASPI's projections are trained as soon as the (zero-initialised) flow head moves.
    """

    def __init__(self, channels: int, guide_channels: int, heads: int = 4, gain_init: float = 1e-2):
        super().__init__()
        if channels % heads:
            raise ValueError(f"aspi: channels ({channels}) must be divisible by heads ({heads})")
        self.heads = heads
        self.norm_q = ChannelLayerNorm(channels)
        self.norm_kv = ChannelLayerNorm(guide_channels)
        self.to_q = nn.Conv2d(channels, channels, 1, bias=False)
        self.to_kv = nn.Conv2d(guide_channels, 2 * channels, 1, bias=False)
        self.temperature = nn.Parameter(torch.ones(heads, 1, 1))
        self.project_out = nn.Conv2d(channels, channels, 1, bias=False)
        self.gain = nn.Parameter(torch.full((1, channels, 1, 1), float(gain_init)))

    def attend(self, shallow, guide, return_attn: bool = False):
        """Softmax(QKᵀτ)V after the output projection (before the gain); optionally the attention matrices."""
        q = self.to_q(self.norm_q(shallow))
        k, v = self.to_kv(self.norm_kv(guide.to(shallow.dtype))).chunk(2, dim=1)
        out, attn = transposed_attention(q, k, v, self.heads, self.temperature, return_attn=True)
        out = self.project_out(out)
        return (out, attn) if return_attn else out

    def forward(self, shallow, guide):
        return shallow + self.gain.to(shallow.dtype) * self.attend(shallow, guide)  # Eq. 10


INJECTIONS = {"none": NoInjection, "concat": ConcatInjection, "aspi": ASPI}


def create_injection(name: str, channels: int, guide_channels: int, **cfg) -> nn.Module:
    if name not in INJECTIONS:
        raise D2TurbError(f"unknown injection {name!r}; available: {', '.join(INJECTIONS)}")
    return INJECTIONS[name](channels, guide_channels, **cfg)
