"""AT-Net (Yasarla, Patel: "Learning to Restore Images Degraded by Atmospheric Turbulence Using Uncertainty",
ICIP 2021).

Two convolutional streams of the same topology. A prior stream with Monte-Carlo dropout restores the image K times;
the per-pixel standard deviation of its K samples is the epistemic uncertainty map σ. The main stream receives
[5σ, I_turb] and σ again at its last full-resolution block, and predicts the clean image. Each stream: a 3×3 conv,
Res2Net-style bottleneck blocks (a 1×1 expansion split into 6 groups of grouped 3×3 convs in a hierarchical residual
cascade, 1×1 projection, BatchNorm; each block concatenates its input with its output) with transition layers
(InstanceNorm–ReLU–1×1 conv), working at half resolution after the first block; the half-scale input enters at the
second block and a half-scale restoration is predicted from the sixth; one-channel side maps of eight intermediate
features join the full-resolution head, which predicts a residual, subtracts it from the input and refines the
result with a 7×7 and a 3×3 conv (sigmoid output for the main stream, tanh for the prior stream).

Training (:meth:`ATNet.extra_loss`): besides the project's photometric term on the main output, AT-Net's own terms —
0.33 × the same L1 at half scale, the angular loss (1×) and the gradient angular loss (0.25×) of its public code — and
the prior stream is supervised jointly with the same multi-scale L1 (AT-Net trains it first; see docs/models.md).
Default: 6.97 M parameters, 3.49 M per stream (paper: 3.05 M; see docs/models.md).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from d2turb.models.common import check_input, pad_to_multiple
from d2turb.models.output import ModelOutput, model_output
from d2turb.models.registry import register_model


def _lrelu(t: torch.Tensor) -> torch.Tensor:
    return F.leaky_relu(t, 0.2)


class Res2Block(nn.Module):
    """Res2NeXt bottleneck (base width 16, cardinality 16, scale 6) → cat([x, ReLU(BN(proj) + 1×1(x))])."""

    def __init__(self, cin: int, planes: int, base_width: int = 16, cardinality: int = 16, scale: int = 6):
        super().__init__()
        width = (planes * base_width // 64) * cardinality
        self.width, self.scale = width, scale
        self.expand = nn.Sequential(
            nn.Conv2d(cin, width * scale, 1, bias=False), nn.BatchNorm2d(width * scale), nn.ReLU()
        )
        self.convs = nn.ModuleList(
            nn.Sequential(
                nn.Conv2d(width, width, 3, padding=1, groups=cardinality, bias=False), nn.BatchNorm2d(width), nn.ReLU()
            )
            for _ in range(scale - 1)
        )
        self.project = nn.Sequential(nn.Conv2d(width * scale, planes, 1, bias=False), nn.BatchNorm2d(planes))
        self.shortcut = nn.Conv2d(cin, planes, 1, bias=False)

    def forward(self, x):
        parts = self.expand(x).split(self.width, dim=1)
        outs, sp = [], None
        for i, conv in enumerate(self.convs):  # hierarchical residual cascade over the splits
            sp = conv(parts[i] if sp is None else sp + parts[i])
            outs.append(sp)
        out = self.project(torch.cat(outs + [parts[-1]], 1))
        return torch.cat([x, F.relu(out + self.shortcut(x))], 1)


class Transition(nn.Sequential):
    """InstanceNorm → ReLU → 1×1 conv → dropout (MC dropout in the prior stream: always on)."""

    def __init__(self, cin: int, cout: int, dropout: float):
        super().__init__(nn.InstanceNorm2d(cin), nn.ReLU(), nn.Conv2d(cin, cout, 1, bias=False))
        self.p = dropout

    def forward(self, x):
        return F.dropout(super().forward(x), self.p, training=True) if self.p > 0 else super().forward(x)


class Stream(nn.Module):
    """One AT-Net stream. ``guide_channels`` extra input channels (σ) enter at the input and at the last block.
    forward(x, x_half, σ or None) -> (out, out_half, head feature)."""

    def __init__(self, guide_channels: int, dropout: float, final: str, c: int = 64, res2=(16, 16, 6), in_channels=3):
        super().__init__()
        g, k = guide_channels, in_channels
        self.dropout = dropout
        self.head = nn.Conv2d(k + g, c // 2, 3, padding=1)
        self.block1, self.trans1 = Res2Block(c // 2, c // 2, *res2), Transition(c, c, dropout)  # then 2× avg pool
        self.block2, self.trans2 = Res2Block(c + k, c, *res2), Transition(2 * c + k, c, dropout)
        self.mid = nn.ModuleList(Res2Block(c, c, *res2) for _ in range(5))  # blocks 3, 3_1, 3_2, 3_3, 4
        self.mid_trans = nn.ModuleList(Transition(2 * c, c, dropout) for _ in range(5))
        self.block5 = Res2Block(2 * c, c, *res2)
        self.half_in, self.half_feat = nn.Conv2d(k, 16, 3, padding=1), nn.Conv2d(3 * c, 16, 3, padding=1)
        self.trans5 = nn.Sequential(  # IN-ReLU-1×1, IN-ReLU-3×3, then bilinear 2× up to full resolution
            nn.InstanceNorm2d(3 * c + k), nn.ReLU(), nn.Conv2d(3 * c + k, c, 1, bias=False),
            nn.InstanceNorm2d(c), nn.ReLU(), nn.Conv2d(c, c, 3, padding=1, bias=False),
        )  # fmt: skip
        self.block6, self.trans6 = Res2Block(c + k + g, c, *res2), Transition(2 * c + k + g, 16, dropout)
        self.side = nn.ModuleList(nn.Conv2d(c, 1, 3, padding=1) for _ in range(8))
        self.full_in, self.full_feat = nn.Conv2d(k, 16, 3, padding=1), nn.Conv2d(16 + 8, 16, 3, padding=1)
        self.to_residual = nn.Conv2d(16, k, 3, padding=1)  # shared by both scales
        self.refine1, self.refine2 = nn.Conv2d(k, 8, 7, padding=3), nn.Conv2d(8, k, 3, padding=1)  # shared
        self.final = torch.sigmoid if final == "sigmoid" else torch.tanh

    def _refine(self, x):
        return self.final(self.refine2(_lrelu(self.refine1(x))))

    def forward(self, x, x_half, sigma=None):
        h = _lrelu(self.head(x if sigma is None else torch.cat([sigma, x], 1)))
        x1 = F.avg_pool2d(self.trans1(self.block1(h)), 2)
        x2 = self.trans2(self.block2(torch.cat([x1, x_half], 1)))
        feats, z = [x1, x2], x2
        for block, trans in zip(self.mid, self.mid_trans):
            z = trans(block(z))
            feats.append(z)
        x5i = self.block5(torch.cat([z, x1], 1))
        res_half = torch.tanh(self.to_residual(_lrelu(self.half_in(x_half)) - _lrelu(self.half_feat(x5i))))
        x5 = self.trans5(torch.cat([x5i, res_half], 1))
        x5 = F.interpolate(F.dropout(x5, self.dropout, training=True) if self.dropout else x5, scale_factor=2,
                           mode="bilinear", align_corners=True)  # fmt: skip
        feats.append(x5)
        x6 = self.trans6(self.block6(torch.cat([x5, x] if sigma is None else [x5, x, sigma], 1)))
        size = x6.shape[-2:]
        sides = [
            F.interpolate(_lrelu(conv(f)), size=size, mode="bilinear", align_corners=True)
            for conv, f in zip(self.side, reversed(feats))
        ]
        feat = _lrelu(self.full_in(x)) - _lrelu(self.full_feat(torch.cat([x6, *sides], 1)))
        out = self._refine(x - torch.tanh(self.to_residual(feat)))
        return out, self._refine(x_half - res_half), feat


def angular_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean over images of the angle (radians) between the flattened prediction and target."""
    cos = F.cosine_similarity(pred.flatten(1).float(), target.flatten(1).float(), dim=1, eps=1e-8)
    return torch.acos(cos.clamp(-1 + 1e-6, 1 - 1e-6)).mean()


def gradient_angular_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Angular loss of the horizontal plus that of the vertical finite differences."""
    dx_p, dx_t = pred[..., :, :-1] - pred[..., :, 1:], target[..., :, :-1] - target[..., :, 1:]
    dy_p, dy_t = pred[..., :-1, :] - pred[..., 1:, :], target[..., :-1, :] - target[..., 1:, :]
    return angular_loss(dx_p, dx_t) + angular_loss(dy_p, dy_t)


@register_model("atnet")
class ATNet(nn.Module):
    """forward(image) -> ModelOutput {"deblurred" = "restored", "bwd_flow_px": None, "guide": the main stream's
    16-channel head feature, "uncertainty": σ}; in training also "restored_half", "prior", "prior_half".
    ``mc_samples`` = K (≥ 2); ``width``: channels of the half-resolution blocks; ``base_width``, ``cardinality``,
    ``scale``: the Res2NeXt blocks'."""

    half_weight, angular_weight, gradient_weight = 0.33, 1.0, 0.25  # AT-Net's loss weights
    uncertainty_gain = 5.0  # σ enters the main stream as 5σ

    def __init__(
        self,
        width: int = 64,
        base_width: int = 16,
        cardinality: int = 16,
        scale: int = 6,
        dropout: float = 0.25,
        mc_samples: int = 10,
        in_channels: int = 3,
    ):
        super().__init__()
        if mc_samples < 2 or not 0 < dropout < 1 or width % 4 or scale < 2:
            raise ValueError("atnet: need mc_samples >= 2, 0 < dropout < 1, width divisible by 4 and scale >= 2")
        res2 = (base_width, cardinality, scale)
        self.prior = Stream(0, dropout, "tanh", width, res2, in_channels)
        self.main = Stream(in_channels, 0.0, "sigmoid", width, res2, in_channels)
        self.mc_samples = mc_samples
        self.guide_channels = 16

    def forward(self, image: torch.Tensor) -> ModelOutput:
        check_input(image)
        x, (h, w) = pad_to_multiple(image, 2)
        x_half = F.interpolate(x, scale_factor=0.5)  # nearest, as AT-Net
        extras = {}
        samples = []
        if self.training:  # one prior sample keeps its graph: it is supervised (extra_loss)
            prior, prior_half, _ = self.prior(x, x_half)
            extras["prior"], extras["prior_half"] = prior[..., :h, :w], prior_half
            samples.append(prior.detach())
        with torch.no_grad():  # Monte-Carlo dropout: K stochastic passes, σ = their per-pixel standard deviation
            samples += [self.prior(x, x_half)[0] for _ in range(self.mc_samples - len(samples))]
            sigma = torch.stack(samples).float().std(dim=0).to(x.dtype)
        restored, restored_half, feat = self.main(x, x_half, self.uncertainty_gain * sigma)
        restored = restored[..., :h, :w]
        out = model_output(restored, restored, None, feat[..., :h, :w])
        out.update(extras)
        out["uncertainty"] = sigma[..., :h, :w]
        if self.training:
            out["restored_half"] = restored_half
        return out

    def extra_loss(self, out: dict, batch: dict) -> dict[str, torch.Tensor]:
        """AT-Net's terms beyond L1(restored, gt): 0.33·L1 at half scale, angular and gradient-angular losses, and
        the prior stream's multi-scale L1."""
        if out.get("prior") is None:
            return {}
        gt = batch["gt"].float()
        gt_half = F.interpolate(pad_to_multiple(gt, 2)[0], scale_factor=0.5)

        def l1(a, b):
            return (a.float() - b).abs().mean()

        restored = out["restored"].float()
        return {
            "half": self.half_weight * l1(out["restored_half"], gt_half),
            "angular": self.angular_weight * angular_loss(restored, gt),
            "grad_angular": self.gradient_weight * gradient_angular_loss(restored, gt),
            "prior": l1(out["prior"], gt) + self.half_weight * l1(out["prior_half"], gt_half),
        }
