"""LPIPS (Zhang et al., CVPR 2018), v0.1 "lin" variant, from local weights only (never downloads).

Two files are needed per variant ("alex" or "vgg"):
  * the backbone in torchvision format (``features.0.weight`` ...), e.g. ``alexnet-owt-7be5be79.pth``
    or ``vgg16-397923af.pth``;
  * the LPIPS linear heads (``lin0.model.1.weight`` ... ``lin4.model.1.weight``), i.e. the ``lpips``
    package's ``weights/v0.1/alex.pth`` / ``vgg.pth``.
Each is found, in order, from the explicit argument, the environment variable
(``D2TURB_LPIPS_BACKBONE`` / ``D2TURB_LPIPS_WEIGHTS``: a file, or a folder holding the file names
below), or the cache folder ``$D2TURB_CACHE_DIR`` (default ``~/.cache/d2turb/``). ``.pth``/``.pt``
files are read with ``torch.load(weights_only=True)``; ``.safetensors`` is also accepted.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import nn

from d2turb.errors import D2TurbError
from d2turb.eval.vgg import CHANNELS, FeatureExtractor, load_backbone, load_state_dict_file
from d2turb.io import cache_dir

BACKBONE_NAMES = {
    "alex": ["alexnet.safetensors", "alexnet.pth", "alexnet-owt-7be5be79.pth"],
    "vgg": ["vgg16.safetensors", "vgg16.pth", "vgg16-397923af.pth"],
}
LIN_NAMES = {
    net: [
        f"lpips/{net}.safetensors",
        f"lpips/{net}.pth",
        f"lpips_{net}.safetensors",
        f"lpips_{net}.pth",
        f"{net}.safetensors",
        f"{net}.pth",
    ]
    for net in CHANNELS
}
# Input normalisation of the LPIPS ScalingLayer, applied to images mapped to [-1, 1]
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)


def _find(explicit: str | os.PathLike | None, env: str, names: list[str], what: str, option: str) -> Path:
    if explicit:
        return Path(explicit)
    candidates: list[Path] = []
    if os.environ.get(env):
        given = Path(os.environ[env]).expanduser()
        if not given.is_dir():
            return given
        candidates += [given / Path(n).name for n in names] + [given / n for n in names]
    candidates += [cache_dir() / n for n in names]
    for path in candidates:
        if path.is_file():
            return path
    raise D2TurbError(
        f"LPIPS needs the {what}: pass {option} FILE, set {env}, or put {names[-1]} in {cache_dir()} "
        f"(nothing is downloaded)"
    )


def _lin_head(channels: int) -> nn.Module:
    head = nn.Module()
    head.model = nn.Sequential(nn.Dropout(), nn.Conv2d(channels, 1, 1, bias=False))  # key: linN.model.1.weight
    return head


class LPIPS(nn.Module):
    """LPIPS distance; ``forward(pred, target)`` takes (B, 3, H, W) in [0, 1] and returns (B,) (0 = identical)."""

    def __init__(
        self, net: str = "alex", weights: str | os.PathLike | None = None, backbone: str | os.PathLike | None = None
    ) -> None:
        super().__init__()
        if net not in CHANNELS:
            raise D2TurbError(f"unknown LPIPS network {net!r}; choose 'alex' or 'vgg'")
        self.net = net
        backbone_name = "AlexNet" if net == "alex" else "VGG16"
        backbone_path = _find(
            backbone,
            "D2TURB_LPIPS_BACKBONE",
            BACKBONE_NAMES[net],
            f"{backbone_name} backbone weights (torchvision format)",
            "--lpips-backbone",
        )
        lin_path = _find(
            weights,
            "D2TURB_LPIPS_WEIGHTS",
            LIN_NAMES[net],
            f"LPIPS v0.1 '{net}' linear-layer weights ({net}.pth of the lpips package)",
            "--lpips-weights",
        )
        self.features = load_backbone(FeatureExtractor(net, device="meta"), backbone_path)
        for i, c in enumerate(CHANNELS[net]):
            self.add_module(f"lin{i}", _lin_head(c))
        self._load_lins(lin_path)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def _load_lins(self, path: Path) -> None:
        state = load_state_dict_file(path, f"LPIPS {self.net} linear weights")
        state = {k.removeprefix("module.").replace("lins.", "lin"): v for k, v in state.items()}
        for i, c in enumerate(CHANNELS[self.net]):
            key = f"lin{i}.model.1.weight"
            if key not in state:
                raise D2TurbError(f"LPIPS {self.net} linear weights {path}: missing key {key}")
            if tuple(state[key].shape) != (1, c, 1, 1):
                raise D2TurbError(
                    f"LPIPS {self.net} linear weights {path}: {key} has shape {tuple(state[key].shape)}, "
                    f"expected (1, {c}, 1, 1) (weights of the other network?)"
                )
            getattr(self, f"lin{i}").model[1].weight.data.copy_(state[key].float())

    def forward(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        feats = [self.features((2 * x - 1 - self.shift) / self.scale) for x in (pred, target)]
        total = 0.0
        for i, (f0, f1) in enumerate(zip(*feats)):
            n0 = f0 / (f0.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)  # unit-normalise channels
            n1 = f1 / (f1.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + getattr(self, f"lin{i}").model((n0 - n1) ** 2).mean(dim=(2, 3))
        return total.flatten()


def lpips(pred: torch.Tensor, target: torch.Tensor, net: str = "alex", weights=None, backbone=None) -> torch.Tensor:
    """Functional LPIPS (builds the model on every call; keep an ``LPIPS`` instance for repeated use)."""
    return LPIPS(net, weights, backbone).to(pred.device)(pred, target)
