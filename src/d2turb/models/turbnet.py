"""TurbNet (Mao, Jaiswal, Wang, Chan: "Single Frame Atmospheric Turbulence Mitigation: A Benchmark Study and a New
Physics-Inspired Transformer Model", ECCV 2022).

A Restormer-style transformer U-Net (WithBias LayerNorm) reconstructs the clean image J; a physics-inspired
degradation branch re-degrades it: a second refinement stage on the same decoder feature predicts a turbulence map T,
a pointwise network of the input predicts an additive term ε, and I = T ⊙ J + ε must reproduce the turbulent input.
Training objective: α‖J − I_gt‖ + (1 − α)‖I − I_turb‖ with α = 0.9. Here the first term is the project's
photometric term (weight λ_photo = 1) and :meth:`TurbNet.extra_loss` adds the second with weight (1 − α)/α = 1/9, so
the ratio of the two terms is TurbNet's. The degradation branch only runs in training (inference needs J alone).
Default = the paper configuration: 26.60 M parameters (paper 26.57 M).
"""

from __future__ import annotations

import torch
from torch import nn

from d2turb.models.common import check_input, pad_to_multiple
from d2turb.models.output import ModelOutput, model_output
from d2turb.models.registry import register_model
from d2turb.models.restormer import Restormer, transformer_stage


def restormer_decoder_feature(net: Restormer, x: torch.Tensor) -> torch.Tensor:
    """The level-1 decoder output of a Restormer (before the refinement stage); ``x`` padded to a multiple of 8."""
    e1 = net.encoder_level1(net.patch_embed(x))
    e2 = net.encoder_level2(net.down1_2(e1))
    e3 = net.encoder_level3(net.down2_3(e2))
    lat = net.latent(net.down3_4(e3))
    d3 = net.decoder_level3(net.reduce_chan_level3(torch.cat([net.up4_3(lat), e3], 1)))
    d2 = net.decoder_level2(net.reduce_chan_level2(torch.cat([net.up3_2(d3), e2], 1)))
    return net.decoder_level1(torch.cat([net.up2_1(d2), e1], 1))


@register_model("turbnet")
class TurbNet(Restormer):
    """forward(image) -> ModelOutput {"deblurred" = "restored" = J, "bwd_flow_px": None, "guide": refinement feature}
    and, in training,
    "redegraded": I = T ⊙ J + ε."""

    alpha = 0.9  # TurbNet's weight of the reconstruction term; the re-degradation term has 1 − α

    def __init__(self, **config):  # the fields of RestormerConfig
        super().__init__(**config)
        a = self.arch
        dim, bias, in_channels = a.dim, a.bias, a.in_channels
        self.refinement_t = transformer_stage(
            dim * 2, a.heads[0], a.num_refinement_blocks, a.ffn_expansion, bias, a.norm_bias
        )
        self.output_t = nn.Conv2d(dim * 2, in_channels, 3, padding=1, bias=bias)
        self.epsilon = nn.Sequential(  # ε: a per-pixel network of the turbulent input
            nn.Conv2d(in_channels, 8 * in_channels, 1), nn.ReLU(), nn.Conv2d(8 * in_channels, in_channels, 1)
        )

    def forward(self, image: torch.Tensor) -> ModelOutput:
        check_input(image)
        x, (h, w) = pad_to_multiple(image, self.multiple)
        d1 = restormer_decoder_feature(self, x)
        guide = self.refinement(d1)
        clean = self.output(guide)[..., :h, :w] + image  # J
        out = model_output(clean, clean, None, guide[..., :h, :w])
        if self.training:
            turb_map = self.output_t(self.refinement_t(d1))[..., :h, :w]  # T
            out["redegraded"] = turb_map * clean + self.epsilon(image)  # I = T ⊙ J + ε
        return out

    def extra_loss(self, out: dict, batch: dict) -> dict[str, torch.Tensor]:
        """(1 − α)/α · ‖I − I_turb‖₁ (mean absolute error), the re-degradation term."""
        if out.get("redegraded") is None:
            return {}
        err = (out["redegraded"].float() - batch["turb"].float()).abs().mean()
        return {"redegrade": (1 - self.alpha) / self.alpha * err}
