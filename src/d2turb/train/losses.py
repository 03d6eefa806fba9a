"""Multi-stage objective of Sec. 3.3: L_total = L_deblur + λ_flow·L_flow + L_detilt (Eq. 11–14).

* L_deblur = the backbone's native loss between Î_tilt and I_tilt (Eq. 11); Restormer and NAFNet: L1
  (``NATIVE_LOSS``; NAFNet's paper loss, PSNR-loss, is available as ``native: psnr``).
* L_flow = ‖V̂ − V_bwd‖₁ (Eq. 12), mean absolute error in pixels.
* L_detilt = λ_photo‖Î_clean − I_gt‖₁ + λ_vgg‖φ(Î_clean) − φ(I_gt)‖²₂ (Eq. 13); φ = VGG16 relu1_2…relu5_3 on
  ImageNet-normalised input, the squared norm taken as the mean squared difference per layer, summed over layers.
* Plain backbones (flow None, Table 1 baselines): λ_photo·L1(restored, I_gt) (+ λ_vgg·VGG term); with an explicit
  ``loss.native`` (e.g. ``psnr``), λ_photo·that loss against I_gt instead of L1 (``plain=`` of MultiStageLoss).
* Optional, beyond the paper: λ_spec·‖|F(Î_clean)| − |F(I_gt)|‖₁ (``loss.spectral``), the L1 distance of the 2-D
  Fourier amplitudes (orthonormal FFT, per channel). A shift changes only the phase of a spectrum, so this term
  asks for the clean image's sharpness while hardly caring where the unknown tilt put each edge; the PSNR or L1
  term alone aims at the conditional mean, which the tilt blurs (MODEL_CARD.md).
* A method's own extra terms (e.g. TurbNet's re-degradation), already weighted: ``model.extra_loss(out, batch)`` or,
  failing that, its backbone's (see :func:`extra_loss_of`).
All norms are means over elements, so a batch split across processes averages to the full-batch loss.
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import nn

from d2turb.errors import D2TurbError
from d2turb.eval.vgg import FeatureExtractor, imagenet_normalize, load_backbone


def l1_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return (pred - target).abs().mean()


def psnr_loss(pred: torch.Tensor, target: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """NAFNet's PSNR loss: mean over images of 10·log10(MSE + eps), i.e. −PSNR in dB for data range 1."""
    mse = (pred - target).pow(2).flatten(1).mean(1)
    return (10.0 / math.log(10.0)) * torch.log(mse + eps).mean()


def spectral_amplitude_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean |(|F pred| − |F target|)| over channels and frequencies; F = orthonormal 2-D real FFT (Parseval: the
    same scale as a per-pixel difference). Shape: (B, C, H, W) each."""
    amp_pred = torch.fft.rfft2(pred.float(), norm="ortho").abs()
    amp_target = torch.fft.rfft2(target.float(), norm="ortho").abs()
    return (amp_pred - amp_target).abs().mean()


NATIVE_LOSSES: dict[str, Callable[[torch.Tensor, torch.Tensor], torch.Tensor]] = {"l1": l1_loss, "psnr": psnr_loss}
# Per-backbone native objective (Eq. 11). A backbone class may also declare ``native_loss = "..."``.
NATIVE_LOSS: dict[str, str] = {"restormer": "l1", "nafnet": "l1"}


def native_loss_name(model: nn.Module, override: str | None = None) -> str:
    """The name of the native deblurring loss of ``model``'s backbone (``override`` wins; default l1)."""
    if override is not None:
        name = override
    else:
        backbone = getattr(model, "backbone", None)
        config = getattr(backbone, "config", {}) or {}
        name = getattr(backbone, "native_loss", None) or NATIVE_LOSS.get(config.get("name"), "l1")
    if name not in NATIVE_LOSSES:
        raise D2TurbError(f"unknown native loss {name!r}; choose from {', '.join(NATIVE_LOSSES)}")
    return name


class PerceptualLoss(nn.Module):
    """Σ_layers mean((φ_l(a) − φ_l(b))²) with φ = VGG16 features (frozen) on ImageNet-normalised input."""

    def __init__(self, extractor: nn.Module):
        super().__init__()
        self.extractor = extractor.eval().requires_grad_(False)

    @classmethod
    def from_file(cls, path: str | os.PathLike) -> PerceptualLoss:
        return cls(load_backbone(FeatureExtractor("vgg", device="meta"), path))

    def train(self, mode: bool = True):  # the extractor always stays in eval mode
        super().train(mode)
        self.extractor.eval()
        return self

    def forward(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        feats = self.extractor(imagenet_normalize(torch.cat([pred, target])))
        return sum(F.mse_loss(*f.float().chunk(2)) for f in feats)


class MultiStageLoss(nn.Module):
    """``forward(outputs, batch) -> (total, terms)``; ``terms`` maps each term name to its unweighted value."""

    def __init__(
        self,
        deblur: float = 1.0,
        flow: float = 5.0,
        photo: float = 1.0,
        vgg: float = 0.02,
        perceptual: nn.Module | None = None,
        native: str = "l1",
        extra: Callable[[dict, dict], dict] | None = None,
        plain: str = "l1",
        spectral: float = 0.0,
    ):
        super().__init__()
        for name in (native, plain):
            if name not in NATIVE_LOSSES:
                raise D2TurbError(f"unknown native loss {name!r}; choose from {', '.join(NATIVE_LOSSES)}")
        self.plain = plain  # the photometric loss of a plain backbone (flow None) against I_gt
        self.w_deblur, self.w_flow, self.w_photo = float(deblur), float(flow), float(photo)
        self.w_vgg = float(vgg) if perceptual is not None else 0.0
        self.w_spectral = float(spectral)
        self.perceptual, self.native, self.extra = perceptual, native, extra

    def forward(self, out: dict, batch: dict) -> tuple[torch.Tensor, dict[str, float]]:
        restored, gt = out["restored"].float(), batch["gt"]
        two_stage = out.get("bwd_flow_px") is not None
        photo = l1_loss if two_stage else NATIVE_LOSSES[self.plain]  # Eq. 13, first term (plain: l1 or psnr)
        terms: dict[str, torch.Tensor] = {"photo": photo(restored, gt)}
        total = self.w_photo * terms["photo"]
        if self.w_vgg > 0:
            terms["vgg"] = self.perceptual(restored, gt)  # Eq. 13, second term
            total = total + self.w_vgg * terms["vgg"]
        if self.w_spectral > 0:
            terms["spectral"] = spectral_amplitude_loss(restored, gt)
            total = total + self.w_spectral * terms["spectral"]
        if two_stage:  # two-stage model; plain baselines train on the clean target only
            terms["deblur"] = NATIVE_LOSSES[self.native](out["deblurred"].float(), batch["tilt"])  # Eq. 11
            terms["flow"] = l1_loss(out["bwd_flow_px"].float(), batch["bwd_flow_px"])  # Eq. 12
            total = total + self.w_deblur * terms["deblur"] + self.w_flow * terms["flow"]  # Eq. 14
        for name, value in (self.extra(out, batch) if self.extra is not None else {}).items():
            terms[name] = value
            total = total + value
        return total, {k: float(v.detach()) for k, v in terms.items()}


def extra_loss_of(model: nn.Module) -> Callable[[dict, dict], dict] | None:
    """``model.extra_loss`` or else ``model.backbone.extra_loss``: ``(out, batch) -> {name: weighted term}``."""
    return getattr(model, "extra_loss", None) or getattr(getattr(model, "backbone", None), "extra_loss", None)


def build_loss(loss_cfg: dict, model: nn.Module, device="cpu", warn: bool = True) -> MultiStageLoss:
    """The loss of a config's ``loss`` section (a mapping of :class:`d2turb.train.config.LossConfig`'s fields).

    No ``vgg_weights``: the perceptual term is disabled with one ``UserWarning`` (``warn``); a given path that does
    not exist is an error. Never downloads."""
    perceptual = None
    if loss_cfg.get("vgg", 0) > 0:
        path = loss_cfg.get("vgg_weights")
        if path:
            perceptual = PerceptualLoss.from_file(path).to(device)
        elif warn:
            warnings.warn("loss.vgg_weights not set; the VGG perceptual term (λ_vgg) is disabled", stacklevel=2)
    return MultiStageLoss(
        deblur=loss_cfg.get("deblur", 1.0),
        flow=loss_cfg.get("flow", 5.0),
        photo=loss_cfg.get("photo", 1.0),
        vgg=loss_cfg.get("vgg", 0.02),
        perceptual=perceptual,
        native=native_loss_name(model, loss_cfg.get("native")),
        extra=extra_loss_of(model),
        plain=native_loss_name(model, loss_cfg["native"]) if loss_cfg.get("native") else "l1",
        spectral=loss_cfg.get("spectral", 0.0),
    )
