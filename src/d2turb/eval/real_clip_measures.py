"""The measures of the real clips report (:mod:`d2turb.eval.real_clips`): the residual frame-to-frame motion, the
camera's shake and the frames it moved most, what a person sees in a frame (:mod:`d2turb.eval.artifacts`) and where
it is worst, NIQE / PIQE, and which of issue 49's acceptance 3 a method fails.

The report's columns (``COLUMNS``): the input frame, the default's fused frame before its deblur (the mean fusion:
``--deblur none --fusion mean``), ``--deblur none`` (the sharpest fusion) and the default.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import torch

from d2turb.clip.registration import DenseFlow, global_shift_px, to_gray_u8, to_hwc
from d2turb.errors import D2TurbError
from d2turb.eval import artifacts
from d2turb.eval.artifacts import worst_window
from d2turb.eval.niqe import niqe
from d2turb.eval.piqe import piqe
from d2turb.restore.clip_source import clip_frames

MOTION_PRESET = "fast"  # DIS preset of the residual-motion measurement (the restoration's default registration)
SHAKE_FRAMES = 3  # the ghost check: this many frames farthest from the middle frame's pose, and as many nearest
SHAKE_SIDE_PX = 512  # the shake is measured on frames scaled to this longer side
COLUMNS = ("input", "mean", "none", "default")
METHODS = COLUMNS[1:]
LABELS = {
    "input": "input",
    "mean": "mean fusion (default, no deblur)",
    "none": "--deblur none (sharpest fusion)",
    "default": "default (blind deblur)",
}
TAIL_RISE_MAX = 0.5  # percentage points of near-black or near-white pixels a method may add (issue 49, acc. 3)


# ---- measurements --------------------------------------------------------------------------------------------------
class MotionMeter:
    """Residual frame-to-frame motion of a stream of frames: per consecutive pair the mean |DIS flow| (px) of the
    later frame onto the earlier (:class:`~d2turb.clip.registration.DenseFlow`); ``median`` over the pairs."""

    def __init__(self, preset: str = MOTION_PRESET):
        self.flow = DenseFlow(preset)
        self.previous: np.ndarray | None = None
        self.values: list[float] = []

    def add(self, frame) -> None:
        """Add the next frame ((3,H,W) tensor or (H,W,3) array in [0,1])."""
        grey = to_gray_u8(to_hwc(frame))
        if self.previous is not None:
            f = self.flow(self.previous, grey)
            self.values.append(float(np.sqrt((f**2).sum(axis=2)).mean()))
        self.previous = grey

    @property
    def median(self) -> float:
        return float(np.median(self.values)) if self.values else math.nan


def textured_window(image: torch.Tensor, size: int) -> tuple[int, int]:
    """(y, x) of the ``size``² window of ``image`` with the most gradient energy (sum of |∇ luma|²), on an 8 px
    grid: where the crops of the sheet show detail, halos and ringing."""
    g = to_gray_u8(to_hwc(image)).astype(np.float32) / 255
    gx, gy = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    return worst_window(gx * gx + gy * gy, size)


# ---- the camera's shake --------------------------------------------------------------------------------------------
def camera_shifts(src: Path, max_frames: int) -> list[float]:
    """Each frame's global shift from the middle frame (|(dx, dy)| px, phase correlation of the luma scaled to
    ``SHAKE_SIDE_PX``): the camera's shake, with the turbulence's jitter of the whole frame. One read of the clip's
    first ``max_frames`` frames (unreadable ones skipped, as the restoration skips them)."""
    _, frames = clip_frames(src, SimpleNamespace(record=lambda exc: None))
    small, scale = [], 1.0
    for frame in itertools.islice(frames, max_frames):
        grey = to_gray_u8(to_hwc(frame))
        scale = min(1.0, SHAKE_SIDE_PX / max(grey.shape))
        if scale < 1.0:
            size = (max(2, round(grey.shape[1] * scale)), max(2, round(grey.shape[0] * scale)))
            grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
        small.append(grey)
    if not small:
        return []
    middle = small[len(small) // 2]
    return [float(np.hypot(*global_shift_px(middle, g, max_side=SHAKE_SIDE_PX))) / scale for g in small]


def shake_frames(shifts: list[float], count: int = SHAKE_FRAMES) -> tuple[list[int], list[int]]:
    """(the ``count`` frames farthest from the middle frame's pose, the ``count`` nearest and not among those)."""
    order = sorted(range(len(shifts)), key=lambda i: (-shifts[i], i))
    shaken = sorted(order[:count])
    calm = sorted([i for i in reversed(order) if i not in shaken][:count])
    return shaken, calm


# ---- the measures of one frame -------------------------------------------------------------------------------------
def frame_measures(image, reference) -> dict[str, float]:
    """What a person sees in ``image`` (:mod:`d2turb.eval.artifacts`), the flat blocks and strong edges those of
    ``reference`` (its input frame): near_black / near_white (share of pixels, %), block (B/A), noise (σ, grey
    levels), sharpness (peak gradient at the input's strongest edges, grey levels per px)."""
    black, white = artifacts.tail_fractions(image)
    return {
        "near_black": 100 * black,
        "near_white": 100 * white,
        "block": artifacts.block_energy(image),
        "noise": 255 * artifacts.flat_noise_sigma(image, reference),
        "sharpness": 255 * artifacts.edge_sharpness(image, reference),
    }


def worst_windows(frames: dict[str, np.ndarray], shaken: dict[str, np.ndarray] | None, side: int) -> dict:
    """Per crop of ``CROPS``: (y, x) of the default's worst ``side``² window against the input on the sheet's
    frame (``frames``: {column: (H,W,3) uint8}), the ghost's on the most shaken frame (``shaken``, None: the sheet's
    frame)."""
    inp, out = frames["input"], frames["default"]
    tails = np.abs(artifacts.tail_map(out)).astype(np.float32) - np.abs(artifacts.tail_map(inp))
    shaken = frames if shaken is None else shaken
    badness = {
        "tails": tails,
        "blocks": artifacts.block_map(out) - artifacts.block_map(inp),
        "noise": artifacts.noise_map(out, inp) - artifacts.noise_map(inp),
        "sharpness": artifacts.sharpness_loss_map(out, inp),
        "ghost": artifacts.ghost_map(shaken["default"], shaken["input"]),
    }
    windows = {"textured": textured_window(inp, side)}
    windows.update({k: worst_window(v, side) for k, v in badness.items()})
    return windows


def niqe_piqe(image: torch.Tensor, notes: set) -> dict[str, float]:
    """NIQE and PIQE of an image; a metric that cannot score it (too small, flat) is NaN, its reason in ``notes``."""
    image = image.clamp(0, 1)
    values = {}
    for name, metric in (("niqe", niqe), ("piqe", piqe)):
        try:
            values[name] = float(metric(image))
        except D2TurbError as exc:
            values[name] = math.nan
            notes.add(str(exc))
    return values


def finite_mean(values: list[float]) -> float:
    finite = [v for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else math.nan


def checks(measures: dict[str, dict], ghost_excess: dict[str, float]) -> dict[str, list[str]]:
    """Per method, which of issue 49's acceptance 3 it fails: near-black / near-white share more than
    ``TAIL_RISE_MAX`` points above the input's, block grid above the input's, a ghost on the shaken frames, not
    sharper than the input."""
    inp = measures["input"]
    fails = {}
    for m in METHODS:
        v, f = measures[m], []
        if v["near_black"] - inp["near_black"] > TAIL_RISE_MAX:
            f.append("shadows")
        if v["near_white"] - inp["near_white"] > TAIL_RISE_MAX:
            f.append("highlights")
        if v["block"] > inp["block"]:
            f.append("blocks")
        if ghost_excess[m] > artifacts.GHOST_EXCESS_MAX:
            f.append("ghost")
        if not v["sharpness"] > inp["sharpness"]:
            f.append("softer")
        fails[m] = f
    return fails
