"""AlexNet / VGG16 convolutional feature extractors with torchvision's layer layout (no torchvision needed).

The ``features`` Sequential has the same indices as ``torchvision.models.alexnet().features`` and
``torchvision.models.vgg16().features``, so a torchvision state dict (``features.0.weight`` ...) loads
as is. ``forward`` returns the five ReLU outputs used by LPIPS (and by perceptual losses).
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import nn

from d2turb.errors import D2TurbError

# (layer spec, indices of the ReLUs whose outputs are returned)
_ALEX = [
    ("C", 3, 64, 11, 4, 2),
    ("R",),
    ("M",),
    ("C", 64, 192, 5, 1, 2),
    ("R",),
    ("M",),
    ("C", 192, 384, 3, 1, 1),
    ("R",),
    ("C", 384, 256, 3, 1, 1),
    ("R",),
    ("C", 256, 256, 3, 1, 1),
    ("R",),
    ("M",),
]
_ALEX_TAPS = (1, 4, 7, 9, 11)  # relu1 .. relu5
_VGG16_CFG = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"]
_VGG16_TAPS = (3, 8, 15, 22, 29)  # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3

CHANNELS = {"alex": (64, 192, 384, 256, 256), "vgg": (64, 128, 256, 512, 512)}
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def imagenet_normalize(x: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) in [0, 1] → the input torchvision backbones were trained on (for perceptual losses)."""
    mean = torch.tensor(IMAGENET_MEAN, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    return (x - mean) / std


def _alex_layers() -> list[nn.Module]:
    layers: list[nn.Module] = []
    for spec in _ALEX:
        if spec[0] == "C":
            _, cin, cout, k, s, p = spec
            layers.append(nn.Conv2d(cin, cout, k, stride=s, padding=p))
        elif spec[0] == "R":
            layers.append(nn.ReLU(inplace=False))
        else:
            layers.append(nn.MaxPool2d(3, stride=2))
    return layers


def _vgg16_layers() -> list[nn.Module]:
    layers: list[nn.Module] = []
    cin = 3
    for v in _VGG16_CFG:
        if v == "M":
            layers.append(nn.MaxPool2d(2, stride=2))
        else:
            layers += [nn.Conv2d(cin, v, 3, padding=1), nn.ReLU(inplace=False)]
            cin = v
    return layers


class FeatureExtractor(nn.Module):
    """``net`` is "alex" or "vgg" (VGG16). Input: (B, 3, H, W) already normalised as the caller needs."""

    def __init__(self, net: str = "alex", device: str | torch.device | None = None) -> None:
        super().__init__()
        if net not in CHANNELS:
            raise D2TurbError(f"unknown backbone {net!r}; choose 'alex' or 'vgg'")
        self.net = net
        with torch.device(device or "cpu"):  # "meta": no random init, for weights loaded right after
            layers = _alex_layers() if net == "alex" else _vgg16_layers()
        self.taps = _ALEX_TAPS if net == "alex" else _VGG16_TAPS
        self.features = nn.Sequential(*layers[: self.taps[-1] + 1])  # nothing after the last tap is needed

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        outs = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.taps:
                outs.append(x)
        return outs


def load_state_dict_file(path: str | os.PathLike, what: str) -> dict[str, torch.Tensor]:
    """A state dict from ``.safetensors`` or a torch file (``weights_only=True``); one-line errors."""
    path = Path(path)
    if not path.is_file():
        raise D2TurbError(f"{what}: no such file {path}")
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(path))
        else:
            state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # corrupt / unsafe pickle / wrong format
        raise D2TurbError(f"{what}: cannot load {path} ({exc.__class__.__name__})") from exc
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise D2TurbError(f"{what}: {path} does not contain a state dict of tensors")
    return state


def load_backbone(extractor: FeatureExtractor, path: str | os.PathLike) -> FeatureExtractor:
    """Load torchvision-format weights (``features.N.weight``; classifier keys are ignored)."""
    state = load_state_dict_file(path, f"{extractor.net} backbone")
    state = {k.removeprefix("module."): v for k, v in state.items()}
    wanted = extractor.state_dict()
    missing = [k for k in wanted if k not in state]
    if missing:
        raise D2TurbError(
            f"{extractor.net} backbone {path}: missing keys {missing[:3]} (expected torchvision "
            f"{'alexnet' if extractor.net == 'alex' else 'vgg16'} weights)"
        )
    bad = [k for k in wanted if state[k].shape != wanted[k].shape]
    if bad:
        raise D2TurbError(
            f"{extractor.net} backbone {path}: shape mismatch for {bad[0]}: "
            f"{tuple(state[bad[0]].shape)} vs {tuple(wanted[bad[0]].shape)}"
        )
    extractor.load_state_dict({k: state[k].float() for k in wanted}, assign=True)
    return extractor
