"""TMT (Zhang, Mao, Chimitt, Chan: "Imaging through the Atmosphere using Turbulence Mitigation Transformer", IEEE TCI
2024), single-frame mode: the multi-scale deblurring transformer fed one frame.

TMT is a Restormer-like U-Net over (frames × H × W) volumes: 3×7×7 embeddings of the input at full, ½ and ¼ scale
(the coarser two are concatenated with the downsampled features of the level above), transformer blocks whose
attention runs across channels and time after a "channel-temporal shuffle" (the qkv channels, in 8 groups, are mixed
across groups by a learned linear map over (group, frame)), gated depthwise feed-forward networks, and a global
residual. With a single frame, every temporal kernel of size 3 sees its outer taps only on zero padding, so the
network reduces exactly to this 2-D one (centre taps only) and the shuffle map to an 8×8 linear map across groups.
Its blocks normalise the residual stream itself (x ← LN(x); x ← x + Attn(x); x ← LN(x); x ← x + FFN(x)).

Default = the configuration of TMT's static-scene training script (blocks 2/3/3/4, heads 1/2/4/8, 2 refinement
blocks, 8 shuffle groups) with one frame: 14.97 M parameters. The paper's 22.75 M counts the 3-D kernels, whose
outer temporal taps never touch a pixel of a single frame: :func:`published_parameter_count` adds them back
(22.745 M). The two-stage TMT's separate tilt-removal network is not part of the single-frame model (nor of 22.75 M).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from d2turb.models.common import ChannelLayerNorm, check_input, pad_to_multiple, transposed_attention
from d2turb.models.output import ModelOutput, model_output
from d2turb.models.registry import register_model
from d2turb.models.restormer import GDFN, RestormerConfig, add_decoder, decode


class ShuffleAttention(nn.Module):
    """Channel(-temporal) attention of TMT for one frame: qkv = DW3×3(Conv1×1(x)); the 3C channels, viewed as
    (groups, 3C/groups), are mixed across groups by a learned linear map and re-ordered (3C/groups, groups) — a
    channel shuffle; then transposed attention with a per-head temperature."""

    def __init__(self, dim: int, heads: int, bias: bool, groups: int = 8):
        super().__init__()
        if (3 * dim) % groups or dim % heads:
            raise ValueError(f"tmt: 3·dim ({3 * dim}) must be divisible by {groups} and dim by heads ({heads})")
        self.heads, self.groups = heads, groups
        self.temperature = nn.Parameter(torch.ones(heads, 1, 1))
        self.qkv = nn.Conv2d(dim, dim * 3, 1, bias=bias)
        self.qkv_dwconv = nn.Conv2d(dim * 3, dim * 3, 3, padding=1, groups=dim * 3, bias=bias)
        self.shuffle = nn.Linear(groups, groups)
        self.project_out = nn.Conv2d(dim, dim, 1, bias=bias)

    def forward(self, x):
        b, _, h, w = x.shape
        qkv = self.qkv_dwconv(self.qkv(x))
        qkv = qkv.reshape(b, self.groups, -1, h, w).permute(0, 2, 3, 4, 1)  # (b, C', h, w, groups)
        qkv = self.shuffle(qkv).permute(0, 1, 4, 2, 3).reshape(b, -1, h, w)  # channel index c'·groups + g
        q, k, v = qkv.chunk(3, dim=1)
        return self.project_out(transposed_attention(q, k, v, self.heads, self.temperature))


class Block(nn.Module):
    def __init__(self, dim: int, heads: int, expansion: float, bias: bool, norm_bias: bool, groups: int):
        super().__init__()
        self.norm1 = ChannelLayerNorm(dim, bias=norm_bias)
        self.attn = ShuffleAttention(dim, heads, bias, groups)
        self.norm2 = ChannelLayerNorm(dim, bias=norm_bias)
        self.ffn = GDFN(dim, expansion, bias)

    def forward(self, x):
        x = self.norm1(x)
        x = x + self.attn(x)
        x = self.norm2(x)
        return x + self.ffn(x)


class Downsample(nn.Sequential):  # conv to cout/4 channels, pixel-unshuffle: (cin, H, W) -> (cout, H/2, W/2)
    def __init__(self, cin: int, cout: int):
        super().__init__(nn.Conv2d(cin, cout // 4, 3, padding=1, bias=False), nn.PixelUnshuffle(2))


@register_model("tmt")
class TMT(nn.Module):
    """forward(image) -> ModelOutput {"deblurred" = "restored", "bwd_flow_px": None, "guide": refinement feature
    (2·dim channels)}."""

    multiple = 8  # three 2× downsamples

    defaults = {"num_blocks": (2, 3, 3, 4), "num_refinement_blocks": 2}  # TMT's own, over RestormerConfig's

    def __init__(self, shuffle_groups: int = 8, **config):  # config: the fields of RestormerConfig
        super().__init__()
        arch = self.arch = RestormerConfig(**{**self.defaults, **config})
        dim, heads, bias, in_channels = arch.dim, arch.heads, arch.bias, arch.in_channels
        if len(arch.num_blocks) != 4 or len(heads) != 4:
            raise ValueError("tmt: num_blocks and heads need 4 entries (levels 1-4)")

        def stage(d, level, n=None):
            n = arch.num_blocks[level] if n is None else n
            return nn.Sequential(
                *[Block(d, heads[level], arch.ffn_expansion, bias, arch.norm_bias, shuffle_groups) for _ in range(n)]
            )

        self.embed1, self.embed2, self.embed3 = (nn.Conv2d(in_channels, dim, 7, padding=3, bias=bias) for _ in range(3))
        self.encoder_level1 = stage(dim, 0)
        self.down1_2 = Downsample(dim, dim)  # + the ½-scale embedding = 2·dim
        self.encoder_level2 = stage(dim * 2, 1)
        self.down2_3 = Downsample(dim * 2, dim * 3)  # + the ¼-scale embedding = 4·dim
        self.encoder_level3 = stage(dim * 4, 2)
        self.down3_4 = Downsample(dim * 4, dim * 8)
        add_decoder(self, stage, arch)

    def forward(self, image: torch.Tensor) -> ModelOutput:
        check_input(image)
        x, (h, w) = pad_to_multiple(image, self.multiple)
        hp, wp = x.shape[-2:]
        x2 = F.interpolate(x, size=(hp // 2, wp // 2), mode="bilinear", align_corners=False)
        x4 = F.interpolate(x, size=(hp // 4, wp // 4), mode="bilinear", align_corners=False)
        e1 = self.encoder_level1(self.embed1(x))
        e2 = self.encoder_level2(torch.cat([self.embed2(x2), self.down1_2(e1)], 1))
        e3 = self.encoder_level3(torch.cat([self.embed3(x4), self.down2_3(e2)], 1))
        guide = decode(self, e1, e2, e3)
        out = self.output(guide)[..., :h, :w] + image
        return model_output(out, out, None, guide[..., :h, :w])


# modules whose TMT kernels are 3 frames deep (3×7×7 embeddings, 3×3×3 resampling / feed-forward / output convs)
_TEMPORAL = (".embed", "down", "up", "ffn.dwconv", "output")


def published_parameter_count(model: TMT) -> int:
    """Parameters of the published 3-D network with one frame: the 2-D model plus the two outer temporal taps of
    every kernel that is 3 frames deep in TMT (dead with one frame: they only ever multiply zero padding)."""
    total = 0
    for name, p in model.named_parameters():
        temporal = p.dim() == 4 and any(key in "." + name for key in _TEMPORAL)
        total += p.numel() * (3 if temporal else 1)
    return total
