"""D²Turb (Sec. 3.2): deblurring backbone → (Î_tilt, F_guide) (Eq. 8); tilt rectifier with injection of F_guide
(Eq. 10) → backward flow V̂; Î_clean = S(Î_tilt, V̂) (Eq. 9). Also the plain-backbone restorers (Table 1 baselines)."""

from __future__ import annotations

import torch
from torch import nn

from d2turb.errors import D2TurbError
from d2turb.models.rectifier import TiltRectifier
from d2turb.models.registry import create_backbone, register_model
from d2turb.ops.warp import warp


def _check_input(image: torch.Tensor) -> None:
    if not isinstance(image, torch.Tensor) or image.ndim != 4 or image.shape[1] != 3 or not image.is_floating_point():
        shape = tuple(image.shape) if isinstance(image, torch.Tensor) else type(image).__name__
        raise D2TurbError(f"model input must be a float tensor (B, 3, H, W), got {shape}")
    if min(image.shape[-2:]) < 2:
        raise D2TurbError(f"model input is too small: {tuple(image.shape[-2:])}")


@register_model("d2turb")
class D2Turb(nn.Module):
    """forward(image (B,3,H,W)) -> {"deblurred": Î_tilt, "restored": Î_clean, "flow": V̂ (B,2,H,W) pixels x,y,
    "guide": F_guide}.

    backbone: a registered backbone name, configured by ``backbone_cfg``; injection: "aspi" | "concat" | "none",
    configured by ``injection_cfg``; ``rectifier_cfg``: TiltRectifier keywords (width, mults, depth,
    residual_bottleneck, flow_mode). Defaults = paper configuration (Restormer + ASPI: 31.88 M parameters;
    paper 31.82 M).
    """

    def __init__(
        self,
        backbone: str = "restormer",
        injection: str = "aspi",
        backbone_cfg: dict | None = None,
        rectifier_cfg: dict | None = None,
        injection_cfg: dict | None = None,
    ):
        super().__init__()
        self.backbone = create_backbone(backbone, **(backbone_cfg or {}))
        try:
            self.rectifier = TiltRectifier(
                self.backbone.guide_channels, injection=injection, injection_cfg=injection_cfg, **(rectifier_cfg or {})
            )
        except (TypeError, ValueError) as exc:
            raise D2TurbError(f"d2turb: bad rectifier/injection config ({exc})") from None

    def forward(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        _check_input(image)
        deblurred, guide = self.backbone(image)  # Eq. 8
        flow = self.rectifier(deblurred, guide)
        # Eq. 9. Sampled in float64: bf16 cannot hold pixel coordinates beyond 256, and float32 round-off in the
        # pixel → grid → pixel conversion alone shifts samples by ~1e-5 px (zero flow must be exactly the identity).
        wide = torch.float32 if deblurred.device.type == "mps" else torch.float64
        restored = warp(deblurred.to(wide), flow.to(wide)).to(deblurred.dtype)
        return {"deblurred": deblurred, "restored": restored, "flow": flow, "guide": guide}


class BackboneRestorer(nn.Module):
    """A plain backbone trained to predict the clean image directly (Table 1 baselines): restored = deblurred."""

    def __init__(self, backbone: str, **backbone_cfg):
        super().__init__()
        self.backbone = create_backbone(backbone, **backbone_cfg)

    def forward(self, image: torch.Tensor) -> dict[str, torch.Tensor | None]:
        _check_input(image)
        out, guide = self.backbone(image)
        return {"deblurred": out, "restored": out, "flow": None, "guide": guide}


@register_model("d2turb_lite")
def d2turb_lite(
    backbone: str = "nafnet",
    injection: str = "aspi",
    backbone_cfg: dict | None = None,
    rectifier_cfg: dict | None = None,
    injection_cfg: dict | None = None,
) -> D2Turb:
    """CPU-friendly preset: the tiny NAFNet backbone and a narrow 4-level rectifier."""
    rect = {"width": 16, "mults": (1, 2, 4, 4, 8), "depth": 4, **(rectifier_cfg or {})}
    return D2Turb(backbone, injection, backbone_cfg, rect, injection_cfg)
