"""NAFNet-style backbone (Chen et al., ECCV 2022): a light, fast deblurring backbone for CPU users.
forward(image) -> (Î_tilt, F_guide) (Eq. 8); F_guide is the decoder feature before the output conv."""

from __future__ import annotations

import torch
from torch import nn

from d2turb.models.common import ChannelLayerNorm, pad_to_multiple
from d2turb.models.registry import register_backbone


class SimpleGate(nn.Module):
    def forward(self, x):
        a, b = x.chunk(2, dim=1)
        return a * b


class NAFBlock(nn.Module):
    """LayerNorm → 1×1 → depthwise 3×3 → SimpleGate → channel attention → 1×1, then a gated FFN; both branches
    enter through learned residual gains (``beta``, ``gamma``, zero-initialised as in NAFNet)."""

    def __init__(self, c: int, dw_expand: int = 2, ffn_expand: int = 2):
        super().__init__()
        dw, ffn = c * dw_expand, c * ffn_expand
        self.norm1 = ChannelLayerNorm(c)
        self.conv1 = nn.Conv2d(c, dw, 1)
        self.conv2 = nn.Conv2d(dw, dw, 3, padding=1, groups=dw)
        self.sca = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Conv2d(dw // 2, dw // 2, 1))
        self.conv3 = nn.Conv2d(dw // 2, c, 1)
        self.norm2 = ChannelLayerNorm(c)
        self.conv4 = nn.Conv2d(c, ffn, 1)
        self.conv5 = nn.Conv2d(ffn // 2, c, 1)
        self.gate = SimpleGate()
        self.beta = nn.Parameter(torch.zeros(1, c, 1, 1))
        self.gamma = nn.Parameter(torch.zeros(1, c, 1, 1))

    def forward(self, inp):
        x = self.gate(self.conv2(self.conv1(self.norm1(inp))))
        y = inp + self.conv3(x * self.sca(x)) * self.beta
        return y + self.conv5(self.gate(self.conv4(self.norm2(y)))) * self.gamma


@register_backbone("nafnet")
class NAFNet(nn.Module):
    def __init__(
        self,
        width: int = 16,
        enc_blocks=(1, 1, 1, 1),
        middle_blocks: int = 1,
        dec_blocks=(1, 1, 1, 1),
        in_channels: int = 3,
    ):
        super().__init__()
        if len(enc_blocks) != len(dec_blocks):
            raise ValueError("nafnet: enc_blocks and dec_blocks need the same length")
        self.intro = nn.Conv2d(in_channels, width, 3, padding=1)
        self.encoders, self.downs, self.ups, self.decoders = (nn.ModuleList() for _ in range(4))
        c = width
        for n in enc_blocks:
            self.encoders.append(nn.Sequential(*[NAFBlock(c) for _ in range(n)]))
            self.downs.append(nn.Conv2d(c, 2 * c, 2, stride=2))
            c *= 2
        self.middle = nn.Sequential(*[NAFBlock(c) for _ in range(middle_blocks)])
        for n in dec_blocks:
            self.ups.append(nn.Sequential(nn.Conv2d(c, c * 2, 1, bias=False), nn.PixelShuffle(2)))
            c //= 2
            self.decoders.append(nn.Sequential(*[NAFBlock(c) for _ in range(n)]))
        self.ending = nn.Conv2d(width, in_channels, 3, padding=1)
        self.multiple = 2 ** len(enc_blocks)
        self.guide_channels = width

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x, (h, w) = pad_to_multiple(image, self.multiple)
        x = self.intro(x)
        skips = []
        for enc, down in zip(self.encoders, self.downs):
            x = enc(x)
            skips.append(x)
            x = down(x)
        x = self.middle(x)
        for dec, up, skip in zip(self.decoders, self.ups, reversed(skips)):
            x = dec(up(x) + skip)
        return self.ending(x)[..., :h, :w] + image, x[..., :h, :w]  # (Î_tilt, F_guide)
