"""Tilt rectifier R (Sec. 3.2): shallow embedding E(Î_tilt), injection of F_guide, a U-Net and a zero-initialised
flow head that predicts the backward flow V̂ (Eq. 9). Untrained, V̂ ≡ 0, i.e. the identity warp."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from d2turb.models.common import pad_to_multiple
from d2turb.models.injection import create_injection


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


class TiltRectifier(nn.Module):
    """U-Net with ``depth`` (3-5) 2× downsamples; channels ``width * mults[i]`` at level i (len(mults) = depth + 1).

    Default: channels 32/32/64/128/256/256, no residual bottleneck: 5.76 M parameters with ASPI, 8.8 G conv MACs at
    256², matching the paper's D²Turb − Restormer budget (31.82 − 26.13 M, 150.5 − 141.0 G).
    flow_mode "pixel": the head predicts pixels; "normalized": it predicts grid units ([-1, 1] spans the image,
    align_corners=True), converted to pixels by (W-1)/2 and (H-1)/2. Either way forward returns pixels.
    """

    def __init__(
        self,
        guide_channels: int,
        injection: str = "aspi",
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

    def forward(self, deblurred: torch.Tensor, guide: torch.Tensor) -> torch.Tensor:
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
            scale = torch.tensor([(w - 1) / 2, (h - 1) / 2], device=flow.device, dtype=flow.dtype)
            flow = flow * scale[None, :, None, None]
        return flow
