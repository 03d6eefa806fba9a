"""AdaIR (Cui, Zamir, Khan, Knoll, Shah, Khan: "AdaIR: Adaptive All-in-One Image Restoration via Frequency Mining
and Modulation", ICLR 2025) as a D²Turb backbone: forward(image) -> (image_out, F_guide), F_guide = the refinement
feature before the output projection (96 channels), as for Restormer.

AdaIR is Restormer (WithBias LayerNorm) with an adaptive frequency learning block (AFLB) after the latent stage and
after decoder levels 3 and 2. An AFLB mines the input image's spectrum (FMiM): an embedding of the resized input is
split by an input-dependent box mask around the spectrum's centre into a low- and a high-frequency map (magnitudes
of the inverse FFTs); each map cross-attends the decoder feature (channel cross-attention); a modulation module
(FMoM) exchanges information between them (the high map's spatial gate weights the low map, the low map's channel
gate weights the high map); the result cross-attends back into the decoder feature through a zero-initialised gain.
Default = the paper configuration: 28.77 M parameters (paper 28.74 M).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from d2turb.models.common import pad_to_multiple, transposed_attention
from d2turb.models.d2turb import D2Turb
from d2turb.models.registry import register_backbone, register_model
from d2turb.models.restormer import Restormer


class ChannelCrossAttention(nn.Module):
    """Transposed (channel) attention with queries from ``x`` and keys/values from ``y`` (same shape)."""

    def __init__(self, dim: int, heads: int, bias: bool):
        super().__init__()
        self.heads = heads
        self.temperature = nn.Parameter(torch.ones(heads, 1, 1))
        self.q = nn.Sequential(
            nn.Conv2d(dim, dim, 1, bias=bias), nn.Conv2d(dim, dim, 3, padding=1, groups=dim, bias=bias)
        )
        self.kv = nn.Sequential(
            nn.Conv2d(dim, 2 * dim, 1, bias=bias), nn.Conv2d(2 * dim, 2 * dim, 3, padding=1, groups=2 * dim, bias=bias)
        )
        self.project_out = nn.Conv2d(dim, dim, 1, bias=bias)

    def forward(self, x, y):
        k, v = self.kv(y).chunk(2, dim=1)
        return self.project_out(transposed_attention(self.q(x), k, v, self.heads, self.temperature))


class FrequencyModulation(nn.Module):
    """FMoM: low·σ(conv7×7[max_c high, mean_c high]) + high·σ(MLP(avg low) + MLP(max low)), then a 1×1 projection."""

    def __init__(self, dim: int):
        super().__init__()
        self.spatial = nn.Conv2d(2, 1, 7, padding=3, bias=False)
        self.mlp = nn.Sequential(
            nn.Conv2d(dim, dim // 16, 1, bias=False), nn.ReLU(), nn.Conv2d(dim // 16, dim, 1, bias=False)
        )
        self.proj = nn.Conv2d(dim, dim, 1)

    def forward(self, low, high):
        spatial = torch.sigmoid(self.spatial(torch.cat([high.amax(1, keepdim=True), high.mean(1, keepdim=True)], 1)))
        channel = torch.sigmoid(self.mlp(F.adaptive_avg_pool2d(low, 1)) + self.mlp(F.adaptive_max_pool2d(low, 1)))
        return self.proj(low * spatial + high * channel)


def _box(n: int, half: torch.Tensor) -> torch.Tensor:
    """Centred box over ``n`` fftshift-ed frequency bins, per sample: forward = AdaIR's hard mask (bins
    ⌊n/2⌋ − k … ⌊n/2⌋ + k − 1 with k = ⌊half⌋), gradient = that of a unit-width sigmoid edge at ±half (straight
    through), so the rate predictor learns. half: (B,) → (B, n)."""
    idx = torch.arange(n, device=half.device, dtype=torch.float32)
    k = half.detach().floor()[:, None]
    hard = ((idx >= n // 2 - k) & (idx < n // 2 + k)).float()
    soft = torch.sigmoid(half[:, None] - (idx - (n // 2 - 0.5)).abs())
    return hard + (soft - soft.detach())


class FrequencyMining(nn.Module):
    """FMiM: embed the image (3×3 conv), predict the mask's relative half-sizes r ∈ (0, 1)² from its global average
    (1×1 → GELU → 1×1 → sigmoid); half-size = ⌊H / freq_div⌋ · r_h bins (likewise W). Returns (high, low) =
    |IFFT(FFT(e)·(1 − M))|, |IFFT(FFT(e)·M)| (FFT normalised "forward", as AdaIR)."""

    def __init__(self, dim: int, freq_div: int, in_channels: int = 3):
        super().__init__()
        self.embed = nn.Conv2d(in_channels, dim, 3, padding=1, bias=False)
        self.rate = nn.Sequential(
            nn.Conv2d(dim, dim // 8, 1, bias=False), nn.GELU(), nn.Conv2d(dim // 8, 2, 1, bias=False)
        )
        self.freq_div = freq_div

    def forward(self, image):
        e = self.embed(image).float()
        h, w = e.shape[-2:]
        r = torch.sigmoid(self.rate(F.adaptive_avg_pool2d(e, 1).to(image.dtype))).float().flatten(1)  # (B, 2)
        mask = _box(h, (h // self.freq_div) * r[:, 0])[:, :, None] * _box(w, (w // self.freq_div) * r[:, 1])[:, None, :]
        spec = torch.fft.fftshift(torch.fft.fft2(e, norm="forward"), dim=(-2, -1))
        mask = mask[:, None]  # (B, 1, H, W): the same box for every channel

        def back(s):
            return torch.fft.ifft2(torch.fft.ifftshift(s, dim=(-2, -1)), norm="forward").abs().to(image.dtype)

        return back(spec * (1 - mask)), back(spec * mask)


class AFLB(nn.Module):
    """Adaptive frequency learning block: y + γ · CA(y, FMoM(CA(low, y), CA(high, y))), γ initialised to 0."""

    def __init__(self, dim: int, heads: int, bias: bool, freq_div: int):
        super().__init__()
        self.mining = FrequencyMining(dim, freq_div)
        self.attend_high = ChannelCrossAttention(dim, heads, bias)
        self.attend_low = ChannelCrossAttention(dim, heads, bias)
        self.modulation = FrequencyModulation(dim)
        self.attend_back = ChannelCrossAttention(dim, heads, bias)
        self.gain = nn.Parameter(torch.zeros(dim, 1, 1))
        self.skip = nn.Parameter(torch.ones(dim, 1, 1))

    def forward(self, image, y):
        image = F.interpolate(image, size=y.shape[-2:], mode="bilinear", align_corners=False)
        high, low = self.mining(image)
        agg = self.modulation(self.attend_low(low, y), self.attend_high(high, y))
        return self.attend_back(y, agg) * self.gain + y * self.skip


@register_backbone("adair")
class AdaIR(Restormer):
    """Restormer (``norm_bias=True``, AdaIR's WithBias LayerNorm) + three AFLBs with ``heads[2]`` heads.
    ``freq_div``: the mask's half-size is at most ⌊size / freq_div⌋ frequency bins (AdaIR: 128)."""

    def __init__(self, freq_div: int = 128, **config):  # config: the fields of RestormerConfig
        super().__init__(**config)
        if freq_div < 1:
            raise ValueError("adair: freq_div must be >= 1")
        dim, heads, bias = self.arch.dim, self.arch.heads, self.arch.bias
        self.fre1 = AFLB(dim * 8, heads[2], bias, freq_div)
        self.fre2 = AFLB(dim * 4, heads[2], bias, freq_div)
        self.fre3 = AFLB(dim * 2, heads[2], bias, freq_div)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x, (h, w) = pad_to_multiple(image, self.multiple)
        e1 = self.encoder_level1(self.patch_embed(x))
        e2 = self.encoder_level2(self.down1_2(e1))
        e3 = self.encoder_level3(self.down2_3(e2))
        lat = self.fre1(x, self.latent(self.down3_4(e3)))
        d3 = self.fre2(x, self.decoder_level3(self.reduce_chan_level3(torch.cat([self.up4_3(lat), e3], 1))))
        d2 = self.fre3(x, self.decoder_level2(self.reduce_chan_level2(torch.cat([self.up3_2(d3), e2], 1))))
        d1 = self.decoder_level1(torch.cat([self.up2_1(d2), e1], 1))
        guide = self.refinement(d1)  # F_guide (Eq. 8)
        return self.output(guide)[..., :h, :w] + image, guide[..., :h, :w]


@register_model("d2turb_adair")
def d2turb_adair(
    injection: str = "aspi",
    backbone_cfg: dict | None = None,
    rectifier_cfg: dict | None = None,
    injection_cfg: dict | None = None,
    rectifier: str = "authors",
):
    """``d2turb`` with ``backbone="adair"`` (supplementary backbone study): the authors' rectifier and ASPI on
    AdaIR's 96-channel F_guide: 34,463,209 parameters = 28,766,086 + 5,697,123 (paper 34.43 M)."""
    return D2Turb("adair", injection, backbone_cfg, rectifier_cfg, injection_cfg, rectifier)
