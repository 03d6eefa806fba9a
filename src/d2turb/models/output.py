"""What every restoration model's ``forward(image)`` returns: a :class:`ModelOutput` dict.

Flows are named by direction: ``bwd_flow_px`` is the backward flow V̂ of the tilt rectifier, in pixels, x then y:
``restored = warp(deblurred, bwd_flow_px)`` (Eq. 9), supervised by the datasets' ``bwd_flow_px`` (Eq. 12). One key per
tensor: the deprecated name ``flow`` is not stored but still read, with a ``DeprecationWarning`` once
(:class:`ModelOutputDict`)."""

from __future__ import annotations

from typing import TypedDict

import torch

from d2turb.deprecation import AliasDict


class _ModelOutputKeys(TypedDict):
    deblurred: torch.Tensor  # Î_tilt (B, 3, H, W)
    restored: torch.Tensor  # Î_clean (B, 3, H, W)
    bwd_flow_px: torch.Tensor | None  # V̂ (B, 2, H, W); None for a model without a rectifier
    guide: torch.Tensor | None  # F_guide (B, C, H, W)


class ModelOutput(_ModelOutputKeys, total=False):
    """The output of a model's forward. Model-specific extras, in training or for analysis:"""

    uncertainty: torch.Tensor  # AT-Net: σ of its Monte-Carlo prior samples
    prior: torch.Tensor  # AT-Net, training
    prior_half: torch.Tensor  # AT-Net, training
    restored_half: torch.Tensor  # AT-Net, training
    redegraded: torch.Tensor  # TurbNet, training: I = T ⊙ J + ε


class ModelOutputDict(AliasDict):
    """The dict a model returns: one key per tensor; the deprecated ``flow`` reads ``bwd_flow_px``."""

    aliases = {"flow": "bwd_flow_px"}
    what = "model output"


def model_output(
    deblurred: torch.Tensor,
    restored: torch.Tensor,
    bwd_flow_px: torch.Tensor | None = None,
    guide: torch.Tensor | None = None,
) -> ModelOutput:
    """A :class:`ModelOutput` (a :class:`ModelOutputDict`: ``flow`` reads ``bwd_flow_px``, warning).

    Shape:
        deblurred, restored: (B, 3, H, W); bwd_flow_px: (B, 2, H, W) in px, x then y, or None; guide: (B, C, H, W).
    """
    return ModelOutputDict(deblurred=deblurred, restored=restored, bwd_flow_px=bwd_flow_px, guide=guide)
