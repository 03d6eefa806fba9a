"""FocalNet (Cui, Ren, Cao, Knoll: "Focal Network for Image Restoration", ICCV 2023) as a D²Turb backbone:
forward(image) -> (image_out, F_guide), F_guide = the full-resolution decoder feature before the output 3×3 conv.

A three-scale convolutional U-Net: shallow convolutional modules (SCM) inject the ½ and ¼ downscaled input, feature
attention modules (FAM) merge them, residual blocks at every scale; at full resolution the residual blocks run on a
channel split whose second half is at half resolution (multi-scale receptive fields); the focal module (dual-domain
selection: a spatial gate from channel max/mean pooling and dilated depthwise convolutions, then a frequency
selection that rescales the high-frequency part x − mean(x)) sits at the bottleneck; coarse heads predict the ¼ and ½
images for the multi-scale training loss. Default = the 8-residual-block configuration: 6.77 M parameters (paper
6.77 M). Training objective (FocalNet): multi-scale L1 + 0.1 · multi-scale L1 of the 2-D FFT (:meth:`extra_loss`).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from d2turb.models.common import pad_to_multiple, pad_to_size
from d2turb.models.d2turb import D2Turb
from d2turb.models.registry import register_backbone, register_model


def _conv(cin: int, cout: int, k: int, stride: int = 1, act: bool = True, transpose: bool = False) -> nn.Sequential:
    if transpose:  # k=4, stride 2: exact 2× upsampling
        conv = nn.ConvTranspose2d(cin, cout, k, stride=stride, padding=k // 2 - 1)
    else:
        conv = nn.Conv2d(cin, cout, k, stride=stride, padding=k // 2)
    return nn.Sequential(conv, nn.GELU()) if act else nn.Sequential(conv)


class ResBlock(nn.Module):
    def __init__(self, c: int):
        super().__init__()
        self.body = nn.Sequential(_conv(c, c, 3), _conv(c, c, 3, act=False))

    def forward(self, x):
        return x + self.body(x)


class SplitResStage(nn.Module):
    """Full-resolution stage: half of the channels stay at full resolution, the other half go through a stride-2
    depthwise conv; each half has its own ``n`` residual blocks; the coarse half is upsampled back and concatenated."""

    def __init__(self, c: int, n: int):
        super().__init__()
        half = c // 2
        self.down = nn.Conv2d(half, half, 2, stride=2, groups=half)
        self.fine = nn.Sequential(*[ResBlock(half) for _ in range(n)])
        self.coarse = nn.Sequential(*[ResBlock(half) for _ in range(n)])

    def forward(self, x):
        x1, x2 = x.chunk(2, dim=1)
        x1, x2 = self.fine(x1), self.coarse(self.down(x2))
        return torch.cat([x1, F.interpolate(x2, size=x1.shape[-2:], mode="bilinear", align_corners=False)], 1)


class SCM(nn.Sequential):
    """Shallow convolutional module: features of a downscaled input image."""

    def __init__(self, c: int):
        super().__init__(
            _conv(3, c // 4, 3),
            _conv(c // 4, c // 2, 1),
            _conv(c // 2, c // 2, 3),
            _conv(c // 2, c, 1, act=False),
            nn.InstanceNorm2d(c, affine=True),
        )


class FocalModule(nn.Module):
    """Dual-domain selection. Spatial: s = conv3×3([max_c x, mean_c x]); y = DW_dil(x)·s + DW3×3(x) (DW_dil = 5×5
    dilation 2 then 7×7 dilation 3, depthwise). Frequency: y' = a·(y − mean_hw y)·y + b·y. Output a₂·y' + b₂·x; a and
    a₂ start at 0 and b, b₂ at 1, so the module starts as the identity."""

    def __init__(self, c: int):
        super().__init__()
        self.spatial = nn.Conv2d(2, 1, 3, padding=1)
        self.dilated = nn.Sequential(
            nn.Conv2d(c, c, 5, padding=4, dilation=2, groups=c), nn.Conv2d(c, c, 7, padding=9, dilation=3, groups=c)
        )
        self.local = nn.Conv2d(c, c, 3, padding=1, groups=c)
        self.freq_a = nn.Parameter(torch.zeros(c, 1, 1))
        self.freq_b = nn.Parameter(torch.ones(c, 1, 1))
        self.out_a = nn.Parameter(torch.zeros(c, 1, 1))
        self.out_b = nn.Parameter(torch.ones(c, 1, 1))

    def forward(self, x):
        gate = self.spatial(torch.cat([x.amax(1, keepdim=True), x.mean(1, keepdim=True)], 1))
        y = self.dilated(x) * gate + self.local(x)
        y = self.freq_a * (y - y.mean(dim=(2, 3), keepdim=True)) * y + self.freq_b * y
        return self.out_a * y + self.out_b * x


def fft_l1(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean absolute difference of the (unnormalised) 2-D FFTs, real and imaginary parts as separate entries."""
    diff = torch.fft.fft2(pred.float() - target.float(), dim=(-2, -1))
    return torch.view_as_real(diff).abs().mean()


def multiscale_fft_loss(outputs: list[torch.Tensor], target: torch.Tensor, fft_weight: float = 0.1) -> dict:
    """FocalNet's objective beyond the full-scale L1 (the project's photometric term): L1 of each coarser output
    against the bilinearly downscaled target ("multiscale"), plus ``fft_weight`` · FFT-L1 summed over all outputs
    ("fft"). ``outputs``: predictions, coarse to fine, the last one at the target's size."""
    terms: dict[str, torch.Tensor] = {}
    fft = None
    for pred in outputs:
        full = pred.shape[-2:] == target.shape[-2:]
        t = target if full else F.interpolate(target, size=pred.shape[-2:], mode="bilinear", align_corners=False)
        if not full:
            l1 = (pred.float() - t).abs().mean()
            terms["multiscale"] = terms["multiscale"] + l1 if "multiscale" in terms else l1
        fft = fft_l1(pred, t) if fft is None else fft + fft_l1(pred, t)
    terms["fft"] = fft_weight * fft
    return terms


@register_backbone("focalnet")
class FocalNet(nn.Module):
    """Three scales with ``base_channels`` · (1, 2, 4) channels and ``num_res`` residual blocks per stage
    (``num_res=4``: the 3.74 M dehazing/desnowing release; 8: the 6.77 M configuration of the D²Turb comparison)."""

    multiple = 4  # two 2× downsamples
    fft_weight = 0.1  # λ of FocalNet's frequency loss

    def __init__(self, base_channels: int = 32, num_res: int = 8, in_channels: int = 3):
        super().__init__()
        c = base_channels
        if c % 8 or num_res < 1:
            raise ValueError("focalnet: base_channels must be a multiple of 8 and num_res >= 1")
        self.head = _conv(in_channels, c, 3)
        self.enc1 = SplitResStage(c, num_res)
        self.down1 = _conv(c, 2 * c, 3, stride=2)
        self.scm2, self.fam2 = SCM(2 * c), _conv(4 * c, 2 * c, 3, act=False)
        self.enc2 = nn.Sequential(*[ResBlock(2 * c) for _ in range(num_res)])
        self.down2 = _conv(2 * c, 4 * c, 3, stride=2)
        self.scm4, self.fam4 = SCM(4 * c), _conv(8 * c, 4 * c, 3, act=False)
        self.enc3 = nn.Sequential(*[ResBlock(4 * c) for _ in range(num_res)])
        self.focal = FocalModule(4 * c)
        self.dec3 = nn.Sequential(*[ResBlock(4 * c) for _ in range(num_res)])
        self.out4 = _conv(4 * c, 3, 3, act=False)
        self.up3 = _conv(4 * c, 2 * c, 4, stride=2, transpose=True)
        self.fuse2 = _conv(4 * c, 2 * c, 1)
        self.dec2 = nn.Sequential(*[ResBlock(2 * c) for _ in range(num_res)])
        self.out2 = _conv(2 * c, 3, 3, act=False)
        self.up2 = _conv(2 * c, c, 4, stride=2, transpose=True)
        self.fuse1 = _conv(2 * c, c, 1)
        self.dec1 = SplitResStage(c, num_res)
        self.output = nn.Conv2d(c, in_channels, 3, padding=1)
        self.guide_channels = c
        self._side: list[torch.Tensor] | None = None

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x, (h, w) = pad_to_multiple(image, self.multiple)
        x2 = F.interpolate(x, scale_factor=0.5)  # nearest, as in FocalNet
        x4 = F.interpolate(x2, scale_factor=0.5)
        e1 = self.enc1(self.head(x))
        e2 = self.enc2(self.fam2(torch.cat([self.down1(e1), self.scm2(x2)], 1)))
        z = self.enc3(self.fam4(torch.cat([self.down2(e2), self.scm4(x4)], 1)))
        z = self.dec3(self.focal(z))
        side4 = self.out4(z) + x4
        z = self.dec2(self.fuse2(torch.cat([self.up3(z), e2], 1)))
        side2 = self.out2(z) + x2
        guide = self.dec1(self.fuse1(torch.cat([self.up2(z), e1], 1)))  # F_guide (Eq. 8)
        out = self.output(guide) + x
        # the coarse predictions only feed the training loss (extra_loss); padded sizes, as is the target there
        self._side = [side4, side2, out] if self.training else None
        return out[..., :h, :w], guide[..., :h, :w]

    def extra_loss(self, out: dict, batch: dict) -> dict[str, torch.Tensor]:
        """FocalNet's terms beyond the full-scale L1: coarse-scale L1 and 0.1 · FFT-L1 at all scales, against the
        clean image for a standalone restorer and against the tilt-only image inside D²Turb (Eq. 11). The predictions
        cover the canvas the backbone saw (the input padded to a multiple of 4, or of 32 inside D²Turb); the target
        is padded to that canvas by the same rule as the input."""
        side, self._side = self._side, None
        if side is None:
            return {}
        target = batch["gt"] if out.get("bwd_flow_px") is None else batch["tilt"]
        target = pad_to_size(target.float(), side[-1].shape[-2:])
        return multiscale_fft_loss(side, target, self.fft_weight)


@register_model("d2turb_focalnet")
def d2turb_focalnet(
    injection: str = "aspi",
    backbone_cfg: dict | None = None,
    rectifier_cfg: dict | None = None,
    injection_cfg: dict | None = None,
    rectifier: str = "authors",
):
    """``d2turb`` with ``backbone="focalnet"`` (supplementary backbone study): the authors' rectifier and ASPI on
    FocalNet's 32-channel F_guide: 12,460,991 parameters = 6,767,964 + 5,693,027 (paper 12.46 M)."""
    return D2Turb("focalnet", injection, backbone_cfg, rectifier_cfg, injection_cfg, rectifier)
