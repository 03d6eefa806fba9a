"""What every restoration model's ``forward(image)`` returns: a :class:`ModelOutput` dict.

Flows are named by direction: ``bwd_flow_px`` is the backward flow V̂ of the tilt rectifier, in pixels, x then y:
``restored = warp(deblurred, bwd_flow_px)`` (Eq. 9), supervised by the datasets' ``bwd_flow_px`` (Eq. 12)."""

from __future__ import annotations

from typing import TypedDict

import torch


class _ModelOutputKeys(TypedDict):
    deblurred: torch.Tensor  # Î_tilt (B, 3, H, W)
    restored: torch.Tensor  # Î_clean (B, 3, H, W)
    bwd_flow_px: torch.Tensor | None  # V̂ (B, 2, H, W); None for a model without a rectifier
    guide: torch.Tensor | None  # F_guide (B, C, H, W)
    flow: torch.Tensor | None  # deprecated name of bwd_flow_px (the same tensor)
    pixel_flow: torch.Tensor | None  # deprecated name of bwd_flow_px (the authors' name; the same tensor)


class ModelOutput(_ModelOutputKeys, total=False):
    """The output of a model's forward. Model-specific extras, in training or for analysis:"""

    uncertainty: torch.Tensor  # AT-Net: σ of its Monte-Carlo prior samples
    prior: torch.Tensor  # AT-Net, training
    prior_half: torch.Tensor  # AT-Net, training
    restored_half: torch.Tensor  # AT-Net, training
    redegraded: torch.Tensor  # TurbNet, training: I = T ⊙ J + ε


def model_output(
    deblurred: torch.Tensor,
    restored: torch.Tensor,
    bwd_flow_px: torch.Tensor | None = None,
    guide: torch.Tensor | None = None,
) -> ModelOutput:
    """A :class:`ModelOutput` with the deprecated names of ``bwd_flow_px`` beside it.

    Shape:
        deblurred, restored: (B, 3, H, W); bwd_flow_px: (B, 2, H, W) in px, x then y, or None; guide: (B, C, H, W).
    """
    return ModelOutput(
        deblurred=deblurred,
        restored=restored,
        bwd_flow_px=bwd_flow_px,
        guide=guide,
        flow=bwd_flow_px,
        pixel_flow=bwd_flow_px,
    )
