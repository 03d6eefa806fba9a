"""Registration of turbulent frames to a reference: a global shift (camera motion) and a dense displacement field
(the tilt), both from OpenCV — phase correlation and DIS optical flow (Kroeger et al., ECCV 2016). Used by clip
restoration (``d2turb.clip``) and by turbulence measurement from a clip.

Convention (the dataset's ``flow``, docs/flow.md): a *backward* flow ``bwd_flow_px`` maps a frame onto the
reference, ``frame(x + bwd_flow_px(x)) ≈ ref(x)``, i.e. ``warp(frame, bwd_flow_px) ≈ ref``; (2, H, W), x then y,
in pixels. Arrays here are numpy (OpenCV's types): grey frames (H, W) uint8, colour frames (H, W, C) float32.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from d2turb.device import usable_cores
from d2turb.errors import D2TurbError

# DIS settings: the tilt of long-range turbulence has structure of a few pixels, so the finest scale is full
# resolution; patch 8 / stride 3 and variational refinement were chosen on simulated clips (docs/clips.md).
DIS_PRESETS = {
    "fast": dict(finest_scale=1, patch_size=8, patch_stride=4, grad_descent_iter=12, var_iter=1),
    "medium": dict(finest_scale=0, patch_size=8, patch_stride=3, grad_descent_iter=16, var_iter=3),
    "fine": dict(finest_scale=0, patch_size=8, patch_stride=2, grad_descent_iter=25, var_iter=5),
}
# OpenCV's DIS refuses images under 12 px (cv2.error) and crashed by SIGSEGV on 11x40 in OpenCV 5.0.0: checked first
MIN_SIDE_PX = 12
LUMA_BT601 = np.array([0.299, 0.587, 0.114], dtype=np.float32)  # ITU-R BT.601, as OpenCV's cvtColor
# a frame of at least this many pixels is "large" (1080p is 2 MP): the clip room decides some of its statistics at half
# size there and registers and deblurs it more cheaply (state.py, stages.py, deblur.py say what and how it measured)
LARGE_FRAME_PIXELS = 1 << 20
_UNIT_OF_U8 = np.arange(256, dtype=np.float32) / np.float32(255)  # k/255 in float32


def is_large_frame(height: int, width: int) -> bool:
    """Whether a frame of ``height`` × ``width`` px is at least ``LARGE_FRAME_PIXELS``."""
    return height * width >= LARGE_FRAME_PIXELS


def check_registrable(height: int, width: int) -> None:
    """One-line ``D2TurbError`` for frames too small to register (both sides must be >= ``MIN_SIDE_PX``)."""
    if min(height, width) < MIN_SIDE_PX:
        raise D2TurbError(f"frames of {width}x{height} are too small to register (need {MIN_SIDE_PX} px per side)")


def to_hwc(frame) -> np.ndarray:
    """A (3,H,W) tensor or (H,W[,C]) array in [0,1] (uint8: 0–255) → C-contiguous (H,W,C) float32 in [0,1]."""
    if isinstance(frame, torch.Tensor):
        frame = frame.detach().cpu().float()
        if frame.ndim != 3:
            raise D2TurbError(f"expected a (C,H,W) frame, got shape {tuple(frame.shape)}")
        frame = frame.permute(1, 2, 0).numpy()
    arr = np.asarray(frame)
    arr = unit_float(arr) if arr.dtype == np.uint8 else np.asarray(arr, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3:
        raise D2TurbError(f"expected an (H,W,C) frame, got shape {arr.shape}")
    return np.ascontiguousarray(arr)


def unit_float(image: np.ndarray) -> np.ndarray:
    """A uint8 image as float32 k/255, the same values as ``image.astype(np.float32) / np.float32(255)`` (OpenCV's
    table lookup, without numpy's float temporary: about half the time on a 1080p frame; OpenCV returns nothing for
    an empty image, numpy's path takes it)."""
    if image.size and (image.ndim == 2 or (image.ndim == 3 and image.shape[2] <= 4)):
        return cv2.LUT(image, _UNIT_OF_U8).reshape(image.shape)
    return image.astype(np.float32) / np.float32(255)


def to_gray_u8(frame_hwc: np.ndarray) -> np.ndarray:
    """(H,W,C) float in [0,1] → (H,W) uint8 luma (what DIS and phase correlation take)."""
    if frame_hwc.shape[2] == 1:
        gray = frame_hwc[..., 0] * 255.0
    else:
        gray = frame_hwc[..., :3] @ LUMA_BT601
        gray *= 255.0  # in place (the product is this function's own), in its dtype, as gray * 255.0 would be
    gray += 0.5
    return np.clip(gray, 0, 255, out=gray).astype(np.uint8)


@functools.lru_cache(maxsize=4)
def _hann(shape: tuple[int, int]) -> np.ndarray:
    return cv2.createHanningWindow(shape[::-1], cv2.CV_32F)


def global_shift_px(ref_gray: np.ndarray, frame_gray: np.ndarray, max_side: int = 512) -> tuple[float, float]:
    """The translation (dx, dy) with ``frame(x + (dx, dy)) ≈ ref(x)``, to a fraction of a pixel, by phase correlation
    with a Hann window (``cv2.phaseCorrelate``); frames larger than ``max_side`` are correlated at a reduced size
    (area averaging) and the shift scaled back: it only starts the dense registration."""
    (a, scale), (b, _) = shrunk(ref_gray, max_side), shrunk(frame_gray, max_side)
    return shrunk_shift_px(a, b, scale)


def shrunk(gray: np.ndarray, max_side: int = 512) -> tuple[np.ndarray, float]:
    """(the grey as float32, reduced by area averaging to at most ``max_side`` px a side, the scale applied)."""
    a = gray.astype(np.float32)
    scale = min(1.0, max_side / max(a.shape))
    if scale < 1.0:
        size = (max(2, round(a.shape[1] * scale)), max(2, round(a.shape[0] * scale)))
        a = cv2.resize(a, size, interpolation=cv2.INTER_AREA)
    return a, scale


def shrunk_shift_px(ref: np.ndarray, frame: np.ndarray, scale: float) -> tuple[float, float]:
    """:func:`global_shift_px` of two greys already :func:`shrunk` by ``scale``, in full-size px."""
    (dx, dy), _ = cv2.phaseCorrelate(ref, frame, _hann(ref.shape))
    return float(dx) / scale, float(dy) / scale


@dataclass
class DenseFlow:
    """Dense backward flow of a frame onto a reference with OpenCV's DIS (one solver reused for every call).

    Args:
        preset: one of ``DIS_PRESETS`` ("fast", "medium", "fine").
        coarser: pyramid levels above the preset's finest scale where the search stops (0: the preset; 1: the flow
            at half the preset's resolution, upsampled by DIS: about a third of the time at 1080p).
        patch_stride: the patches' stride in px (None: the preset's).
    """

    preset: str = "medium"
    coarser: int = 0
    patch_stride: int | None = None

    def __post_init__(self):
        if self.preset not in DIS_PRESETS:
            raise D2TurbError(f"unknown registration preset {self.preset!r}; choose one of {', '.join(DIS_PRESETS)}")
        cv2.setNumThreads(usable_cores())
        s = DIS_PRESETS[self.preset]
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        dis.setFinestScale(s["finest_scale"] + self.coarser)
        dis.setPatchSize(s["patch_size"])
        dis.setPatchStride(s["patch_stride"] if self.patch_stride is None else self.patch_stride)
        dis.setGradientDescentIterations(s["grad_descent_iter"])
        dis.setVariationalRefinementIterations(s["var_iter"])
        dis.setUseMeanNormalization(True)  # robust to the frame-to-frame brightness flicker of scintillation
        dis.setUseSpatialPropagation(True)
        self._dis = dis

    def __call__(self, ref_gray: np.ndarray, frame_gray: np.ndarray, init: np.ndarray | None = None) -> np.ndarray:
        """``bwd_flow_px`` (H,W,2) float32 with ``frame(x + flow(x)) ≈ ref(x)``; ``init`` (H,W,2) starts the search.

        Shape:
            ref_gray, frame_gray: (H, W) uint8, H, W ≥ 2.
        """
        if ref_gray.shape != frame_gray.shape or ref_gray.dtype != np.uint8 or frame_gray.dtype != np.uint8:
            raise D2TurbError(f"registration needs two (H,W) uint8 images of one size, got {ref_gray.shape}")
        check_registrable(*ref_gray.shape)
        start = None if init is None else np.ascontiguousarray(init, dtype=np.float32)
        return self._dis.calc(ref_gray, frame_gray, start)


def remap(
    frame_hwc: np.ndarray, bwd_flow_px: np.ndarray, consume: bool = False, interpolation: int = cv2.INTER_LINEAR
) -> np.ndarray:
    """``frame(x + flow(x))`` by bilinear interpolation (or ``interpolation``, an OpenCV flag; ``cv2.remap``, edges
    replicated), (H,W,C) of the frame's dtype (float32, or uint8 rounded to nearest and saturated). ``consume``: the
    flow (float32) is the caller's to give up, and becomes the absolute coordinates in place (1080p: a 16.6 MB array
    fewer).

    Shape:
        frame_hwc: (H, W, C); bwd_flow_px: (H, W, 2), x then y.
    """
    grid = pixel_grid(bwd_flow_px.shape[:2])
    # absolute coordinates (H,W,2), one map for cv2.remap
    maps = np.add(bwd_flow_px, grid, out=bwd_flow_px) if consume else bwd_flow_px + grid
    out = cv2.remap(frame_hwc, maps, None, interpolation, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(frame_hwc.shape)


# The last round resamples the frames it fuses bicubically (stages.register). Averaged over uniform fractional
# shifts u, a mean of frames resampled bilinearly has the response E[(1 − u) + u·e^{i2πf}]·e^{−i2πfu} per axis, and
# one resampled by OpenCV's bicubic a larger one; their ratio is fitted by least squares over 0.03–0.45 cycles/px
# with the kernel [a, 1 − 2a, a] (response 1 − 4a·sin²(πf)): a = 0.073.
BILINEAR_MEAN_TAP = 0.073


def as_bilinear_mean(image_chw: torch.Tensor) -> torch.Tensor:
    """A mean of bicubically registered frames as it would be had they been registered bilinearly: each channel
    filtered by the separable [a, 1 − 2a, a], a = ``BILINEAR_MEAN_TAP`` (edges reflected). What a deblur tuned on
    bilinear means reads (``clip.blind.BlindDeblur``).

    Shape:
        image_chw: (C, H, W) float32; output: the same, a new tensor.
    """
    a = BILINEAR_MEAN_TAP
    k = np.array([a, 1 - 2 * a, a], np.float32)
    planes = np.ascontiguousarray(image_chw.detach().float().cpu().numpy())  # a view where it already is
    out = np.empty(planes.shape, np.float32)  # each plane filtered into its place (1080p: no list, no stacked copy)
    for src, dst in zip(planes, out):
        cv2.sepFilter2D(src, cv2.CV_32F, k, k, dst=dst, borderType=cv2.BORDER_REFLECT)
    return torch.from_numpy(out)


@functools.lru_cache(maxsize=4)
def pixel_grid(shape: tuple[int, int]) -> np.ndarray:
    """(H,W,2) float32 of each pixel's own (x, y), read-only (cached: shared by every call of one size)."""
    h, w = shape
    grid = np.empty((h, w, 2), dtype=np.float32)
    grid[..., 0] = np.arange(w, dtype=np.float32)[None, :]
    grid[..., 1] = np.arange(h, dtype=np.float32)[:, None]
    grid.flags.writeable = False
    return grid


def shift_maps(shape: tuple[int, int], dx: float, dy: float) -> np.ndarray:
    """``pixel_grid(shape) + shift_flow(shape, dx, dy)`` equal to the bit, filled axis by axis: (H,W,2) float32 maps
    of a pure shift for ``cv2.remap`` (1080p: 1.7 ms against 3.1 for the flow and the sum)."""
    h, w = shape
    maps = np.empty((h, w, 2), dtype=np.float32)
    maps[..., 0] = np.arange(w, dtype=np.float32) + np.float32(dx)
    maps[..., 1] = (np.arange(h, dtype=np.float32) + np.float32(dy))[:, None]
    return maps


def shifted(frame_hwc: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """``remap(frame_hwc, shift_flow(shape, dx, dy))`` equal to the bit (bilinear, edges replicated), without the
    flow array: ``frame(x + dx, y + dy)``, (H,W,C) of the frame's dtype."""
    maps = shift_maps(frame_hwc.shape[:2], dx, dy)
    out = cv2.remap(frame_hwc, maps, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(frame_hwc.shape)


def shift_flow(shape: tuple[int, int], dx: float, dy: float) -> np.ndarray:
    """A constant (H,W,2) float32 flow."""
    flow = np.empty((*shape, 2), dtype=np.float32)
    flow[..., 0], flow[..., 1] = dx, dy
    return flow
