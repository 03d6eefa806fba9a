"""Restormer (Zamir et al., CVPR 2022) as a D²Turb deblurring backbone: forward(image) -> (Î_tilt, F_guide)
(Eq. 8), F_guide being the refinement feature right before the output projection.
Default = the paper configuration: widths 48/96/192/384, blocks 4/6/6/8, heads 1/2/4/8, 4 refinement blocks,
FFN expansion 2.66, LayerNorm with bias (Restormer's "WithBias", as in the authors' D²Turb), no conv biases:
26,126,644 parameters (``norm_bias=False``, the BiasFree LayerNorm: 26,111,668)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from d2turb.models.common import ChannelLayerNorm, pad_to_multiple, transposed_attention
from d2turb.models.registry import register_backbone


class MDTA(nn.Module):
    """Multi-Dconv head Transposed Attention."""

    def __init__(self, dim: int, heads: int, bias: bool):
        super().__init__()
        self.heads = heads
        self.temperature = nn.Parameter(torch.ones(heads, 1, 1))
        self.qkv = nn.Conv2d(dim, dim * 3, 1, bias=bias)
        self.qkv_dwconv = nn.Conv2d(dim * 3, dim * 3, 3, padding=1, groups=dim * 3, bias=bias)
        self.project_out = nn.Conv2d(dim, dim, 1, bias=bias)

    def forward(self, x):
        q, k, v = self.qkv_dwconv(self.qkv(x)).chunk(3, dim=1)
        return self.project_out(transposed_attention(q, k, v, self.heads, self.temperature))


class GDFN(nn.Module):
    """Gated-Dconv Feed-forward Network."""

    def __init__(self, dim: int, expansion: float, bias: bool):
        super().__init__()
        hidden = int(dim * expansion)
        self.project_in = nn.Conv2d(dim, hidden * 2, 1, bias=bias)
        self.dwconv = nn.Conv2d(hidden * 2, hidden * 2, 3, padding=1, groups=hidden * 2, bias=bias)
        self.project_out = nn.Conv2d(hidden, dim, 1, bias=bias)

    def forward(self, x):
        x1, x2 = self.dwconv(self.project_in(x)).chunk(2, dim=1)
        return self.project_out(F.gelu(x1) * x2)


class TransformerBlock(nn.Module):
    def __init__(self, dim: int, heads: int, expansion: float, bias: bool, norm_bias: bool):
        super().__init__()
        self.norm1 = ChannelLayerNorm(dim, bias=norm_bias)
        self.attn = MDTA(dim, heads, bias)
        self.norm2 = ChannelLayerNorm(dim, bias=norm_bias)
        self.ffn = GDFN(dim, expansion, bias)

    def forward(self, x):
        x = x + self.attn(self.norm1(x))
        return x + self.ffn(self.norm2(x))


def transformer_stage(dim, heads, n, expansion, bias, norm_bias):
    """``n`` transformer blocks of width ``dim`` in a row (one level of the encoder, decoder or refinement)."""
    return nn.Sequential(*[TransformerBlock(dim, heads, expansion, bias, norm_bias) for _ in range(n)])


class Downsample(nn.Sequential):  # conv halves channels, pixel-unshuffle: (C, H, W) -> (2C, H/2, W/2)
    def __init__(self, dim: int):
        super().__init__(nn.Conv2d(dim, dim // 2, 3, padding=1, bias=False), nn.PixelUnshuffle(2))


class Upsample(nn.Sequential):  # conv doubles channels, pixel-shuffle: (C, H, W) -> (C/2, 2H, 2W)
    def __init__(self, dim: int):
        super().__init__(nn.Conv2d(dim, dim * 2, 3, padding=1, bias=False), nn.PixelShuffle(2))


@dataclass
class RestormerConfig:
    """The shape of a Restormer-style transformer U-Net, shared by Restormer, AdaIR, TurbNet and TMT (the paper's
    Restormer by default). Their constructors take these fields as keywords, as ``create_model`` passes a config.

    Args:
        dim: channels of level 1 (levels 2-4: 2, 4, 8 times as many).
        num_blocks: transformer blocks of levels 1-4 (the decoder repeats levels 1-3).
        heads: attention heads of levels 1-4.
        num_refinement_blocks: transformer blocks of the refinement stage (whose output is F_guide).
        ffn_expansion: hidden channels of the gated feed-forward network, per channel.
        bias: biases of the convolutions.
        norm_bias: LayerNorm with bias (Restormer's "WithBias"); False: "BiasFree".
        in_channels: channels of the image.
    """

    dim: int = 48
    num_blocks: Sequence[int] = (4, 6, 6, 8)
    heads: Sequence[int] = (1, 2, 4, 8)
    num_refinement_blocks: int = 4
    ffn_expansion: float = 2.66
    bias: bool = False
    norm_bias: bool = True
    in_channels: int = 3


def add_decoder(module: nn.Module, stage, arch: RestormerConfig) -> None:
    """The latent level, decoder, refinement and output of the Restormer U-Net (the layout Restormer, AdaIR, TurbNet
    and TMT share), set on ``module`` after its encoder (``patch_embed`` or embeddings, ``encoder_level1-3``,
    ``down1_2``, ``down2_3``, ``down3_4``), in the order that makes their state_dict keys and parameter order:
    latent, up4_3, reduce_chan_level3, decoder_level3, up3_2, reduce_chan_level2, decoder_level2, up2_1,
    decoder_level1, refinement, output. ``stage(channels, level, n=None)``: the blocks of one level (``n`` of
    them, else ``arch.num_blocks[level]``)."""
    dim, bias = arch.dim, arch.bias
    module.latent = stage(dim * 8, 3)
    module.up4_3 = Upsample(dim * 8)
    module.reduce_chan_level3 = nn.Conv2d(dim * 8, dim * 4, 1, bias=bias)
    module.decoder_level3 = stage(dim * 4, 2)
    module.up3_2 = Upsample(dim * 4)
    module.reduce_chan_level2 = nn.Conv2d(dim * 4, dim * 2, 1, bias=bias)
    module.decoder_level2 = stage(dim * 2, 1)
    module.up2_1 = Upsample(dim * 2)
    module.decoder_level1 = stage(dim * 2, 0)
    module.refinement = stage(dim * 2, 0, arch.num_refinement_blocks)
    module.output = nn.Conv2d(dim * 2, arch.in_channels, 3, padding=1, bias=bias)
    module.guide_channels = dim * 2


def decode(module: nn.Module, e1: torch.Tensor, e2: torch.Tensor, e3: torch.Tensor) -> torch.Tensor:
    """The refinement feature (``2·dim`` channels) from the encoder's levels 1-3 through the layers of
    :func:`add_decoder` (the level-3 features go down once more to the latent level first)."""
    lat = module.latent(module.down3_4(e3))
    d3 = module.decoder_level3(module.reduce_chan_level3(torch.cat([module.up4_3(lat), e3], 1)))
    d2 = module.decoder_level2(module.reduce_chan_level2(torch.cat([module.up3_2(d3), e2], 1)))
    d1 = module.decoder_level1(torch.cat([module.up2_1(d2), e1], 1))
    return module.refinement(d1)


@register_backbone("restormer")
class Restormer(nn.Module):
    """Restormer(**config): the fields of :class:`RestormerConfig` as keywords; ``self.arch`` holds them."""

    multiple = 8  # three 2× downsamples

    def __init__(self, **config):
        super().__init__()
        arch = self.arch = RestormerConfig(**config)
        dim, heads, bias, in_channels = arch.dim, arch.heads, arch.bias, arch.in_channels
        if len(arch.num_blocks) != 4 or len(heads) != 4:
            raise ValueError("restormer: num_blocks and heads need 4 entries (levels 1-4)")

        def stage(d, level, n=None):
            n = arch.num_blocks[level] if n is None else n
            return transformer_stage(d, heads[level], n, arch.ffn_expansion, bias, arch.norm_bias)

        self.patch_embed = nn.Conv2d(in_channels, dim, 3, padding=1, bias=bias)  # overlapped patch embedding
        self.encoder_level1 = stage(dim, 0)
        self.down1_2 = Downsample(dim)
        self.encoder_level2 = stage(dim * 2, 1)
        self.down2_3 = Downsample(dim * 2)
        self.encoder_level3 = stage(dim * 4, 2)
        self.down3_4 = Downsample(dim * 4)
        add_decoder(self, stage, arch)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x, (h, w) = pad_to_multiple(image, self.multiple)
        e1 = self.encoder_level1(self.patch_embed(x))
        e2 = self.encoder_level2(self.down1_2(e1))
        e3 = self.encoder_level3(self.down2_3(e2))
        guide = decode(self, e1, e2, e3)  # F_guide (Eq. 8)
        return self.output(guide)[..., :h, :w] + image, guide[..., :h, :w]  # global residual
