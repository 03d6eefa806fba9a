"""D²Turb (Sec. 3.2): deblurring backbone → (Î_tilt, F_guide) (Eq. 8); tilt rectifier with injection of F_guide
(Eq. 10) → backward flow V̂; Î_clean = S(Î_tilt, V̂) (Eq. 9). Also the plain-backbone restorers (Table 1 baselines)."""

from __future__ import annotations

import torch
from torch import nn

from d2turb.errors import D2TurbError
from d2turb.models.common import check_input, pad_to_multiple
from d2turb.models.output import ModelOutput, model_output
from d2turb.models.rectifier import create_rectifier
from d2turb.models.registry import create_backbone, register_model, register_standalone
from d2turb.ops.warp import warp


@register_model("d2turb")
class D2Turb(nn.Module):
    """D²Turb. forward(image (B,3,H,W)) -> :class:`~d2turb.models.output.ModelOutput`: {"deblurred": Î_tilt,
    "restored": Î_clean, "bwd_flow_px": V̂ (B,2,H,W) in pixels, x then y, "guide": F_guide} (and the deprecated
    name "flow" of V̂ still read, with a DeprecationWarning).

    Defaults = the paper configuration, exactly the authors' model (31,823,767 parameters): ``restormer`` backbone
    (LayerNorm with bias, 26,126,644), the authors' rectifier (``rectifier="authors"``) and ASPI
    (``injection="aspi"``). The whole pipeline runs on the input padded at the bottom/right to a multiple of 32
    (reflect when the pad is smaller than the side, else replicate): backbone, rectifier and the warp see the padded
    image, and every output is cropped back to H×W.

    Args:
        backbone: a registered backbone name, configured by ``backbone_cfg``.
        injection: "aspi" (authors') | "aspi_cosine" | "concat" | "none", configured by ``injection_cfg``.
        rectifier: "authors" (``rectifier_cfg``: ``widths``) | "unet" (``width``, ``mults``, ``depth``,
            ``residual_bottleneck``, ``flow_mode``).
    """

    multiple = 32  # the authors' padding of the whole pipeline

    def __init__(
        self,
        backbone: str = "restormer",
        injection: str = "aspi",
        backbone_cfg: dict | None = None,
        rectifier_cfg: dict | None = None,
        injection_cfg: dict | None = None,
        rectifier: str = "authors",
    ):
        super().__init__()
        self.backbone = create_backbone(backbone, **(backbone_cfg or {}))
        try:
            self.rectifier = create_rectifier(
                rectifier, self.backbone.guide_channels, injection, injection_cfg, **(rectifier_cfg or {})
            )
        except (TypeError, ValueError) as exc:
            raise D2TurbError(f"d2turb: bad rectifier/injection config ({exc})") from exc

    def forward(self, image: torch.Tensor) -> ModelOutput:
        check_input(image)
        h, w = image.shape[-2:]
        x, _ = pad_to_multiple(image, self.multiple)
        deblurred, guide = self.backbone(x)  # Eq. 8
        flow = self.rectifier(deblurred, guide, size=(h, w))
        # Eq. 9, on the padded image. Sampled in float64: bf16 cannot hold pixel coordinates beyond 256, and float32
        # round-off in the pixel → grid → pixel conversion alone shifts samples by ~1e-5 px (zero flow must be
        # exactly the identity).
        wide = torch.float32 if deblurred.device.type == "mps" else torch.float64
        restored = warp(deblurred.to(wide), flow.to(wide)).to(deblurred.dtype)
        return model_output(deblurred[..., :h, :w], restored[..., :h, :w], flow[..., :h, :w], guide[..., :h, :w])


@register_standalone
class BackboneRestorer(nn.Module):
    """A plain backbone trained to predict the clean image directly (Table 1 baselines): restored = deblurred."""

    def __init__(self, backbone: str, **backbone_cfg):
        super().__init__()
        self.backbone = create_backbone(backbone, **backbone_cfg)

    def forward(self, image: torch.Tensor) -> ModelOutput:
        check_input(image)
        out, guide = self.backbone(image)
        return model_output(out, out, None, guide)


@register_model("d2turb_lite")
def d2turb_lite(
    backbone: str = "nafnet",
    injection: str = "aspi_cosine",
    backbone_cfg: dict | None = None,
    rectifier_cfg: dict | None = None,
    injection_cfg: dict | None = None,
    rectifier: str = "unet",
) -> D2Turb:
    """CPU-friendly preset (1.90 M parameters): the default tiny NAFNet backbone, our variants ``rectifier="unet"``
    (width 16, mults (1, 2, 4, 4, 8), depth 4) and ``injection="aspi_cosine"``; not the authors' architecture."""
    rect = (
        {"width": 16, "mults": (1, 2, 4, 4, 8), "depth": 4, **(rectifier_cfg or {})}
        if rectifier == "unet"
        else rectifier_cfg
    )
    return D2Turb(backbone, injection, backbone_cfg, rect, injection_cfg, rectifier)


@register_model("d2turb_small")
def d2turb_small(
    backbone: str = "nafnet",
    injection: str = "aspi_cosine",
    backbone_cfg: dict | None = None,
    rectifier_cfg: dict | None = None,
    injection_cfg: dict | None = None,
    rectifier: str = "authors",
) -> D2Turb:
    """The shipped CPU model (2.56 M parameters): the authors' rectifier at half width (16/32/64/128/128/128), the
    cosine ASPI variant (attention sharpness independent of image size, so 128² training crops transfer to
    full-size images) and the default NAFNet backbone (width 16). Restores a 1920×1080 frame in seconds on 2 cores."""
    rect = {"widths": (16, 32, 64, 128, 128, 128), **(rectifier_cfg or {})} if rectifier == "authors" else rectifier_cfg
    return D2Turb(backbone, injection, backbone_cfg, rect, injection_cfg, rectifier)
