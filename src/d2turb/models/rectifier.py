"""Tilt rectifier R (Sec. 3.2): shallow embedding F_shallow = E(Î_tilt), injection of F_guide (Eq. 10), an
encoder-decoder and a zero-initialised flow head that predicts the backward flow V̂ in pixels (Eq. 9).
Untrained, V̂ ≡ 0, i.e. the identity warp.

* ``"authors"`` (:class:`TiltRectifier`) — the authors' design, the paper configuration;
* ``"unet"`` (:class:`UNetRectifier`) — our earlier U-Net variant (see docs/models.md).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from d2turb.errors import D2TurbError
from d2turb.models.common import pad_to_multiple
from d2turb.models.injection import create_injection


class ConvGELU(nn.Module):
    """conv3×3 (stride 1 or 2, with bias) + GELU."""

    def __init__(self, cin: int, cout: int, stride: int = 1):
        super().__init__()
        self.body = nn.Sequential(nn.Conv2d(cin, cout, 3, stride=stride, padding=1), nn.GELU())

    def forward(self, x):
        return self.body(x)


class TiltRectifier(nn.Module):
    """The authors' tilt rectifier. With ``widths = (w0, w1, ..., wL)`` (default 32/64/128/256/256/256, L = 5):

    ``input_projection`` conv3×3+GELU (3→w0) gives F_shallow; the injection (``inject``, default the authors' ASPI)
    fuses F_guide into it; ``down_1..L``: stride-2 conv3×3+GELU (w_{i-1}→w_i); ``bottleneck``: two conv3×3+GELU at
    wL; ``decode_L..1``: bilinear ×2 upsampling (align_corners=False), concatenation [upsampled, skip], one
    conv3×3+GELU to w_{i-1}. The skips are the outputs of down_1..L-1 and, at full resolution, F_shallow *before*
    the injection. ``flow_head``: conv3×3 (w0→2) initialised to zero; V̂ is in pixels, x then y.

    Inputs whose sides are not multiples of 2^L are padded (reflect/replicate) and the flow cropped; inside
    :class:`~d2turb.models.D2Turb` the whole pipeline is already padded to a multiple of 32.

    Shape: deblurred (B, 3, H, W), guide (B, G, H, W) -> flow (B, 2, H, W).
    """

    def __init__(
        self,
        guide_channels: int,
        injection: str = "aspi",
        injection_cfg: dict | None = None,
        widths=(32, 64, 128, 256, 256, 256),
        in_channels: int = 3,
    ):
        super().__init__()
        widths = [int(c) for c in widths]
        if len(widths) < 2 or min(widths) < 1:
            raise ValueError(f"rectifier: widths needs at least 2 positive entries, got {widths}")
        self.levels = len(widths) - 1
        self.multiple = 2**self.levels
        self.input_projection = ConvGELU(in_channels, widths[0])
        self.inject = create_injection(injection, widths[0], guide_channels, **(injection_cfg or {}))
        for i in range(1, self.levels + 1):
            self.add_module(f"down_{i}", ConvGELU(widths[i - 1], widths[i], stride=2))
        self.bottleneck = nn.Sequential(ConvGELU(widths[-1], widths[-1]), ConvGELU(widths[-1], widths[-1]))
        for i in range(self.levels, 0, -1):
            self.add_module(f"decode_{i}", ConvGELU(widths[i] + widths[i - 1], widths[i - 1]))  # up: w_i channels
        self.flow_head = nn.Conv2d(widths[0], 2, 3, padding=1)
        nn.init.zeros_(self.flow_head.weight)
        nn.init.zeros_(self.flow_head.bias)

    def forward(self, deblurred: torch.Tensor, guide: torch.Tensor, size=None) -> torch.Tensor:
        """Flow (B, 2, H, W) in pixels. ``size`` (the valid image inside a padded input) is not needed: the head
        predicts pixels directly."""
        h, w = deblurred.shape[-2:]
        x, _ = pad_to_multiple(deblurred, self.multiple)
        guide, _ = pad_to_multiple(guide, self.multiple)
        shallow = self.input_projection(x)  # F_shallow
        skips = [shallow]
        x = self.inject(shallow, guide)  # F_fused (Eq. 10)
        for i in range(1, self.levels + 1):
            x = getattr(self, f"down_{i}")(x)
            skips.append(x)
        x = self.bottleneck(x)
        for i in range(self.levels, 0, -1):
            up = F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False)
            x = getattr(self, f"decode_{i}")(torch.cat([up, skips[i - 1]], 1))
        return self.flow_head(x)[..., :h, :w]


def _conv_block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1),
        nn.LeakyReLU(0.1, inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1),
        nn.LeakyReLU(0.1, inplace=True),
    )


class ResBlock(nn.Module):
    def __init__(self, c: int):
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(c, c, 3, padding=1), nn.LeakyReLU(0.1, inplace=True), nn.Conv2d(c, c, 3, padding=1)
        )

    def forward(self, x):
        return x + self.body(x)


class UNetRectifier(nn.Module):
    """Variant ``rectifier="unet"`` (our earlier design, used by ``d2turb_lite``): embedding conv–LeakyReLU–conv,
    the injection at the input resolution (its output is also the full-resolution skip), then a max-pool U-Net with
    LeakyReLU double convs, ``depth`` (3-5) 2× downsamples, channels ``width * mults[i]`` at level i
    (len(mults) = depth + 1) and an optional residual bottleneck.

    Default: channels 32/32/64/128/256/256, no residual bottleneck: 5.76 M parameters with ``aspi_cosine``, 8.8 G conv
    MACs at 256², chosen to match the paper's D²Turb − Restormer budget (31.82 − 26.13 M, 150.5 − 141.0 G).
    flow_mode "pixel": the head predicts pixels; "normalized": it predicts grid units ([-1, 1] spans the image,
    align_corners=True), converted to pixels by (W-1)/2 and (H-1)/2. Either way forward returns pixels.
    """

    def __init__(
        self,
        guide_channels: int,
        injection: str = "aspi_cosine",
        injection_cfg: dict | None = None,
        width: int = 32,
        mults=(1, 1, 2, 4, 8, 8),
        depth: int = 5,
        residual_bottleneck: bool = False,
        flow_mode: str = "pixel",
        in_channels: int = 3,
    ):
        super().__init__()
        if depth not in (3, 4, 5) or len(mults) != depth + 1:
            raise ValueError(
                f"rectifier: depth must be 3, 4 or 5 with depth + 1 mults (got depth={depth}, mults={mults})"
            )
        if flow_mode not in ("pixel", "normalized"):
            raise ValueError(f"rectifier: flow_mode must be 'pixel' or 'normalized', got {flow_mode!r}")
        self.depth, self.flow_mode, self.multiple = depth, flow_mode, 2**depth
        chans = [width * m for m in mults]
        self.embed = nn.Sequential(
            nn.Conv2d(in_channels, width, 3, padding=1),
            nn.LeakyReLU(0.1, inplace=True),
            nn.Conv2d(width, width, 3, padding=1),
        )  # E (F_shallow)
        self.inject = create_injection(injection, width, guide_channels, **(injection_cfg or {}))
        self.enc = nn.ModuleList(
            [_conv_block(width, chans[0])] + [_conv_block(chans[i - 1], chans[i]) for i in range(1, depth + 1)]
        )
        self.bottleneck = (
            nn.Sequential(ResBlock(chans[-1]), ResBlock(chans[-1])) if residual_bottleneck else nn.Identity()
        )
        self.up = nn.ModuleList([nn.Conv2d(chans[i + 1], chans[i], 3, padding=1) for i in range(depth)])
        self.dec = nn.ModuleList([_conv_block(2 * chans[i], chans[i]) for i in range(depth)])
        self.flow_head = nn.Conv2d(chans[0], 2, 3, padding=1)
        nn.init.zeros_(self.flow_head.weight)
        nn.init.zeros_(self.flow_head.bias)

    def forward(self, deblurred: torch.Tensor, guide: torch.Tensor, size=None) -> torch.Tensor:
        """Flow (B, 2, H, W) in pixels. ``size`` = (h, w) of the image that grid units refer to in
        ``flow_mode="normalized"`` (the valid image inside a padded input; default the input's size)."""
        h, w = deblurred.shape[-2:]
        fused = self.inject(self.embed(deblurred), guide)  # Eq. 10 at the input resolution
        x, _ = pad_to_multiple(fused, self.multiple)
        skips = []
        for i, block in enumerate(self.enc):
            x = block(x if i == 0 else F.max_pool2d(x, 2))
            skips.append(x)
        x = self.bottleneck(x)
        for i in reversed(range(self.depth)):
            x = self.up[i](F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False))
            x = self.dec[i](torch.cat([x, skips[i]], 1))
        flow = self.flow_head(x)[..., :h, :w]
        if self.flow_mode == "normalized":
            h, w = size or (h, w)
            scale = torch.tensor([(w - 1) / 2, (h - 1) / 2], device=flow.device, dtype=flow.dtype)
            flow = flow * scale[None, :, None, None]
        return flow


RECTIFIERS = {"authors": TiltRectifier, "unet": UNetRectifier}


def create_rectifier(name: str, guide_channels: int, injection: str, injection_cfg: dict | None, **cfg) -> nn.Module:
    if name not in RECTIFIERS:
        raise D2TurbError(f"unknown rectifier {name!r}; available: {', '.join(RECTIFIERS)}")
    return RECTIFIERS[name](guide_channels, injection=injection, injection_cfg=injection_cfg, **cfg)
