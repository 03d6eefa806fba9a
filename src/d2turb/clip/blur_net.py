"""Learned blind estimate of a fused frame's blur: the physics parameters of its short-exposure OTF (docs/clips.md,
"the learned blur estimate").

After registration and fusion what is left of the turbulence is a blur of the family the simulator draws: the
tilt-removed mean OTF of ``sim.otf`` at D/r0 and λ/(D·ifov), mixed with the unblurred image by the depth
modulation M (paper Eq. 4: effective OTF M·T·H + (1 − M)). Its scale shows in the width of the frame's edges, and
the two parameters trade off along the registered tilt's spread, which grows as λ/(D·ifov)·(D/r0)^(5/6). A small
CNN reads the fused frame's most textured patches (each normalised to zero mean and unit contrast) and that spread,
and predicts (ln D/r0, ln λ/(D·ifov), logit M) with a log-variance each (Gaussian likelihood); the deblur is then
the physics Wiener filter at those parameters (``PhysicsDeblur``), i.e. what the deblur at the clip's true optics
and strength would do. Trained on fused frames of simulated clips from the train folders of the fixed split, with
optics, strength, wind, noise and JPEG drawn per clip (``benchmarks/blur_net/``). Written here because no library
estimates turbulence blur; the network has 0.04 M parameters, one forward on 8 patches.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import nn

from d2turb.errors import D2TurbError
from d2turb.models.weights import load_state_dict_strict, read_verified

PATCH_PX = 48  # side of the patches read (a few widths of the widest blur trained on, λ/(D·ifov) 4 px at D/r0 5)
PATCH_STRIDE_PX = 24  # candidate patches on a grid of half a patch
# the tilt spread's range on the training clips (5th–95th percentile of ln px; median 0.34, i.e. 1.4 px): the input
# is clamped to it (the network has seen nothing outside), and a frame without a registered flow (a single image)
# reads as the median
TILT_LOG_RANGE = (-0.50, 1.22)
TILT_LOG_UNSEEN = 0.34
SHIPPED = Path(__file__).resolve().parent.parent / "resources" / "blur" / "blur-net.safetensors"
NAME = "blur-net"


def _gray(image) -> np.ndarray:
    """The mean of the channels, (H, W) float32: what the network was trained on (not ``clip.blur``'s luma weights;
    the patches are normalised, so only the channels' mix matters, and changing it means retraining)."""
    a = image.detach().cpu().float().numpy() if isinstance(image, torch.Tensor) else np.asarray(image, np.float32)
    if a.ndim == 3 and a.shape[0] in (1, 3) and a.shape[-1] not in (1, 3):
        a = a.mean(0)
    elif a.ndim == 3:
        a = a.mean(-1)
    return np.ascontiguousarray(a, dtype=np.float32)


def textured_patches(image, count: int) -> np.ndarray:
    """The ``count`` patches of ``PATCH_PX`` with the most gradient energy (a grid of stride ``PATCH_STRIDE_PX``),
    each normalised to zero mean and unit standard deviation (the blur shows in the shape of edges, not their
    contrast).

    Args:
        image: (3,H,W) / (1,H,W) tensor or (H,W[,C]) array in [0, 1].
    Returns:
        (count, PATCH_PX, PATCH_PX) float32; fewer when the image holds fewer patches.
    """
    g = _gray(image)
    h, w = g.shape
    if min(h, w) < PATCH_PX:
        raise D2TurbError(f"an image of {w}x{h} is too small for the learned blur estimate (need {PATCH_PX} px)")
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    energy = cv2.boxFilter(gx * gx + gy * gy, -1, (PATCH_PX, PATCH_PX))
    ys = np.arange(0, h - PATCH_PX + 1, PATCH_STRIDE_PX)
    xs = np.arange(0, w - PATCH_PX + 1, PATCH_STRIDE_PX)
    score = energy[ys[:, None] + PATCH_PX // 2, xs[None, :] + PATCH_PX // 2].ravel()
    best = np.argsort(-score, kind="stable")[:count]
    out = np.stack([g[ys[i // xs.size] : ys[i // xs.size] + PATCH_PX, xs[i % xs.size] : xs[i % xs.size] + PATCH_PX]
                    for i in best])  # fmt: skip
    out -= out.mean((1, 2), keepdims=True)
    return out / (out.std((1, 2), keepdims=True) + 0.01)


TILT_SPREAD_FLOOR_PX = 0.05  # added to the rms in tilt_spread, so that a still clip's stays finite


def tilt_spread(bwd_flow_px, moving=None) -> float:
    """ln of the RMS of a registered frame's flow about its rigid motion (px; + 0.05 px so a still clip stays finite):
    the image motion that the blur's two parameters share. The rigid motion, a translation and a small rotation about
    the centre (least squares), is the camera's: the frames are placed on the canvas by a translation only, so a shaken
    camera's roll stays in the flow (field clips: 0.5° is 1.1 px at 128 px from the centre); the pixels of moving
    objects (``moving`` ≥ 0.5, the fallback share) are left out (their flow is their own motion). On turbulence alone
    the rotation is a small part: about the mean, as the network was trained, to within a few percent.

    Shape:
        bwd_flow_px: (2, H, W); moving: (H, W) or None.
    """
    f = np.asarray(bwd_flow_px.detach().cpu() if isinstance(bwd_flow_px, torch.Tensor) else bwd_flow_px, np.float32)
    h, w = f.shape[1:]
    step = max(1, int(math.sqrt(h * w / 65536)))  # about 65k pixels read
    u, v = f[0, ::step, ::step].astype(np.float64), f[1, ::step, ::step].astype(np.float64)
    y, x = np.mgrid[0:h:step, 0:w:step].astype(np.float64)
    keep = np.ones(u.shape, bool)
    if moving is not None:
        m = np.asarray(moving.detach().cpu() if isinstance(moving, torch.Tensor) else moving)[::step, ::step] < 0.5
        keep = m if m.mean() >= 0.1 else keep  # objects everywhere: nothing to tell them from
    u, v, x, y = u[keep], v[keep], x[keep] - x[keep].mean(), y[keep] - y[keep].mean()
    theta = float((x * v - y * u).sum() / max((x * x + y * y).sum(), 1e-12))  # u = tx − θy, v = ty + θx
    ru, rv = u - u.mean() + theta * y, v - v.mean() - theta * x
    return math.log(float(np.sqrt((ru**2 + rv**2).mean())) + TILT_SPREAD_FLOOR_PX)


class BlurNet(nn.Module):
    """Per patch a 6-layer CNN (two stride-2 stages) pooled to a vector; the vectors averaged over the patches, the
    tilt spread appended, an MLP gives (ln D/r0, ln λ/(D·ifov), logit M) and their log-variances.

    Shape:
        patches: (B, K, P, P); tilt: (B,) → mean (B, 3), log-variance (B, 3).
    """

    def __init__(self, width: int = 16, patches: int = 8, tilt: bool = True):
        super().__init__()
        self.config = {"name": NAME, "width": int(width), "patches": int(patches), "tilt": bool(tilt)}
        w = int(width)
        layers, cin = [], 1
        for cout, stride in ((w, 1), (w, 1), (2 * w, 2), (2 * w, 1), (2 * w, 2), (2 * w, 1)):
            layers += [nn.Conv2d(cin, cout, 3, stride=stride, padding=1), nn.ReLU()]
            cin = cout
        self.features = nn.Sequential(*layers)
        self.head = nn.Sequential(nn.Linear(2 * w + 1, 64), nn.ReLU(), nn.Linear(64, 6))

    def forward(self, patches: torch.Tensor, tilt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b, k = patches.shape[:2]
        f = self.features(patches.reshape(b * k, 1, *patches.shape[2:])).mean((2, 3)).reshape(b, k, -1).mean(1)
        t = tilt.reshape(b, 1).to(f.dtype) if self.config["tilt"] else torch.zeros(b, 1, dtype=f.dtype)
        out = self.head(torch.cat([f, t], 1))
        return out[:, :3], out[:, 3:].clamp(-8.0, 4.0)


def blur_targets(dr0: float, lambda_over_d_px: float, modulation: float) -> torch.Tensor:
    """The network's targets (ln D/r0, ln λ/(D·ifov), logit M) of a clip's true parameters."""
    m = min(max(float(modulation), 1e-3), 1 - 1e-3)
    return torch.tensor([math.log(dr0), math.log(lambda_over_d_px), math.log(m / (1 - m))], dtype=torch.float32)


@dataclass
class LearnedBlur:
    """The network's estimate: each parameter and the standard deviation of its log (logit for M)."""

    dr0: float
    lambda_over_d_px: float
    modulation: float
    log_sd: tuple[float, float, float]

    def as_dict(self) -> dict:
        return asdict(self)


def load_blur_net(path: str | Path | None = None) -> BlurNet:
    """The blur network from a weights file written by ``save_pretrained`` (default: the shipped one), strictly
    loaded and checksum-verified; one ``D2TurbError`` line when it is missing or does not match."""
    path = Path(path) if path is not None else SHIPPED
    tensors, config = read_verified(path)
    if config.pop("name", None) != NAME:
        raise D2TurbError(f"{path}: not a {NAME} weights file")
    try:
        net = BlurNet(**config)
    except TypeError as exc:
        raise D2TurbError(f"{path}: unreadable {NAME} config {config}") from exc
    load_state_dict_strict(net, tensors, str(path))
    return net.eval()


@torch.no_grad()
def estimate_blur_params(fused, bwd_flow_px=None, net: BlurNet | None = None, moving=None) -> LearnedBlur:
    """The learned estimate of a fused frame's blur (see the module's doc).

    Args:
        fused: the fused frame, (3,H,W) tensor or (H,W,3) array in [0, 1], at least ``PATCH_PX`` per side.
        bwd_flow_px: a registered frame's flow (2,H,W) px of the same window (None: a single image, whose spread
            is taken as the training clips' median ``TILT_LOG_UNSEEN``).
        net: the network (default: the shipped weights, loaded once).
        moving: the frame's moving-object share (H,W) (:func:`tilt_spread` leaves those pixels out), or None.
    """
    net = net if net is not None else _shipped_net()
    p = torch.from_numpy(textured_patches(fused, net.config["patches"]))[None]
    t = tilt_spread(bwd_flow_px, moving) if bwd_flow_px is not None else TILT_LOG_UNSEEN
    t = torch.tensor([min(max(t, TILT_LOG_RANGE[0]), TILT_LOG_RANGE[1])])
    mu, log_var = net(p, t)
    mu, sd = mu[0].double(), torch.exp(0.5 * log_var[0].double())
    return LearnedBlur(
        dr0=float(torch.exp(mu[0])),
        lambda_over_d_px=float(torch.exp(mu[1])),
        modulation=float(torch.sigmoid(mu[2])),
        log_sd=tuple(float(s) for s in sd),
    )


_NET: list[BlurNet] = []


def _shipped_net() -> BlurNet:
    if not _NET:
        _NET.append(load_blur_net())
    return _NET[0]


__all__ = ["BlurNet", "LearnedBlur", "blur_targets", "estimate_blur_params", "load_blur_net", "textured_patches"]
