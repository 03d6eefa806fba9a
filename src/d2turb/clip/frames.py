"""The frames of the clip room: what a restored frame is (:class:`ClipFrame`), how an input frame is held while the
windows that read it are computed (:class:`HeldFrame`, one layout: (H,W,C) arrays), and which frames form the window
of an output (:func:`window_start`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from d2turb.clip.registration import to_gray_u8, to_hwc, unit_float

# the last round's unwarped frames (what the fusion averages) are held as 8 bits where the frame is (remapped from the
# 8-bit frame, rounded to nearest: ±0.5 grey levels per frame, about 0.07 after a mean of 16, far below the fusion's
# noise; a quarter of float32), else as float16 (relative error 2^-11)
STORE_DTYPE = np.float16


@dataclass
class ClipFrame:
    """One restored frame: ``restored`` (deblurred fusion), ``fused`` (before deblurring) (3,H,W) float32 tensors
    in [0,1]; ``bwd_flow_px`` (2,H,W) float32 maps the input frame onto the restored geometry,
    ``frame(x + bwd_flow_px(x)) ≈ fused(x)``; ``fallback`` (H,W) in [0,1]: share of the single frame (1 = moving).

    ``bwd_flow_hwc_px`` is that flow as the registration holds it, (H,W,2) float16; ``bwd_flow_px`` is made from it
    when first read (most callers never read it, and it costs 8 ms a 1080p frame).

    ``camera_px`` (dx, dy): the frame's global shift onto the clip's canvas (the first frame's view),
    ``frame(x + camera_px) ≈ canvas(x)``: the camera's motion (shake, jumps) plus the turbulence's whole-frame tilt;
    None without ``stabilise``."""

    index: int
    restored: torch.Tensor
    fused: torch.Tensor
    bwd_flow_hwc_px: np.ndarray
    fallback: torch.Tensor
    _bwd_flow_px: torch.Tensor | None = field(default=None, repr=False)
    camera_px: tuple[float, float] | None = None  # the frame's camera pose on the canvas (``stabilise``), see below

    @property
    def bwd_flow_px(self) -> torch.Tensor:
        if self._bwd_flow_px is None:
            self._bwd_flow_px = torch.from_numpy(self.bwd_flow_hwc_px.transpose(2, 0, 1).astype(np.float32))
        return self._bwd_flow_px


def window_start(index: int, temporal: int, length: int | None, ahead: int | None = None) -> int:
    """First frame of W(index): centred (``ahead`` None), or reaching ``ahead`` frames past ``index`` (its last frame
    index + ahead: a stream's lookahead window, :func:`lookahead_split`); shifted inward at the clip's ends
    (``length`` None: end not known yet)."""
    lo = max(0, index - (temporal // 2 if ahead is None else temporal - 1 - ahead))
    if length is not None:
        lo = min(lo, max(0, length - temporal))
    return lo


def window_span(index: int, temporal: int, length: int | None, ahead: int | None = None) -> tuple[int, int]:
    """[lo, hi) of W(index): from :func:`window_start`, ``temporal`` frames, or up to the clip's end once known."""
    lo = window_start(index, temporal, length, ahead)
    return lo, lo + temporal if length is None else min(length, lo + temporal)


def lookahead_split(lookahead: int | None, temporal: int, passes: int) -> list[int | None]:
    """How far past frame i the window of each level reaches (level 0: the frames, k: registration round k; the
    window over level k is what round k + 1, or the output for k = ``passes``, averages), given that output t may
    wait for input t + ``lookahead`` at most: an output waits for the sum (output t needs level ``passes`` up to
    t + a_passes, frame t + a_passes's last round level passes − 1 up to a_passes + a_(passes−1) further, ...).
    ``lookahead`` None: centred windows at every level (each reaches temporal − 1 − temporal // 2 ahead; a file's
    windows). Else the frames of lookahead are dealt one by one to the levels, the output's first, then the
    rounds' from the last down, none beyond the centred reach; a level given none is causal (W(i) ends at i)."""
    if lookahead is None:
        return [None] * (passes + 1)
    centred = temporal - 1 - temporal // 2
    ahead = [0] * (passes + 1)
    left = lookahead
    while left > 0 and any(a < centred for a in ahead):
        for level in range(passes, -1, -1):
            if left > 0 and ahead[level] < centred:
                ahead[level] += 1
                left -= 1
    return ahead  # all centred when lookahead >= (passes + 1) · centred: the windows of a file


def stream_lookahead(temporal: int) -> int:
    """The lookahead of a stream's windows (``restore -``, :func:`lookahead_split`): temporal/2 − 1 frames, so that an
    output waits for the input half a window later with the threaded deblur's hand-over (one frame), whatever the
    frame rate; centred windows wait for 3·(temporal/2 − 1) with two rounds."""
    return max(0, temporal // 2 - 1)


@dataclass
class HeldFrame:
    """An input frame while the windows that read it are computed (``ClipState.release`` drops what is no longer read).

    Levels: 0 is the frame itself (``raw``; ``gray`` its 8-bit luma, ``canvas_gray`` that luma placed on the clip's
    canvas), k ≥ 1 is registration round k's unwarped frame (``warped[k-1]``)."""

    raw: np.ndarray  # (H,W,C) uint8 when that holds the float32 frame exactly (8-bit input), else float32; see .image
    gray: np.ndarray  # (H,W) uint8
    bwd_flows_px: list = field(default_factory=list)  # the last round's (H,W,2) backward flow onto its reference
    # per round: the frame unwarped; rounds before the last only feed the next round's reference, which DIS reads as
    # 8-bit grey, so they hold the frame's 8-bit luma unwarped, (H,W,1) uint8 (a twelfth of the memory and the remap);
    # the last round, which the fusion averages, the colour frame (H,W,C): uint8 for 8-bit frames, else STORE_DTYPE
    warped: list = field(default_factory=list)
    prepared: object = None  # what the fusion prepared from the last round's image (sharpest: its coefficients)
    coarse: object = None  # fusion "sharpest": coarse grey of the image the last round's reference averages
    canvas_gray: np.ndarray | None = None  # (H,W,1) uint8: the grey placed on the canvas (``stabilise``), else None
    spread_grey: np.ndarray | None = None  # the last round's grey as ``ClipState.spread`` sums it (made once)

    @classmethod
    def of(cls, item) -> HeldFrame:
        """An input frame ((3,H,W) tensor or (H,W,C) array in [0,1], or (H,W,C) uint8) as held (8-bit: as uint8)."""
        raw = to_hwc(item)  # float32 in [0, 1] (an 8-bit frame as k/255)
        gray = to_gray_u8(raw)
        stored = isinstance(item, np.ndarray) and item.dtype == np.uint8 and item.ndim == 3
        return cls(np.ascontiguousarray(item) if stored else compact(raw), gray)

    def image(self) -> np.ndarray:
        """The frame as (H,W,C) float32 in [0,1] (bit-identical to the frame given: k/255 in float32)."""
        return image_of(self.raw)

    def level_float(self, level: int) -> np.ndarray:
        """Level ``level``'s image as float32 in [0, 1]: the frame (0), or round ``level``'s unwarped luma."""
        return self.image() if level == 0 else unit_float(self.warped[level - 1])

    def level_image(self, level: int) -> np.ndarray:
        """Level ``level``'s image as held, as the running sums of the references read it: the frame's 8-bit luma (on
        the canvas when the camera is followed) at level 0, round ``level``'s unwarped image after."""
        if level == 0:
            return self.gray[..., None] if self.canvas_gray is None else self.canvas_gray
        return self.warped[level - 1]


def image_of(raw: np.ndarray) -> np.ndarray:
    """A held frame (uint8 or float) as (H,W,C) float32 in [0, 1] (see :meth:`HeldFrame.image`)."""
    return as_float(raw) if raw.dtype == np.uint8 else raw


def as_float(image: np.ndarray) -> np.ndarray:
    """A held image in [0, 1] as float32 (8-bit ones scaled by 1/255)."""
    return unit_float(image) if image.dtype == np.uint8 else image.astype(np.float32)


def channel_mean(image: np.ndarray) -> np.ndarray:
    """(H,W) float32: the mean over the channels of an (H,W,C) float32 image (``cv2.transform``: a quarter of numpy's
    time at 1080p); a single channel as it is."""
    if image.ndim == 2 or image.shape[2] == 1:
        return image.reshape(image.shape[:2])
    return cv2.transform(image, _CHANNEL_MEAN[image.shape[2]]).reshape(image.shape[:2])


_CHANNEL_MEAN = {c: np.full((1, c), 1 / c, np.float32) for c in (2, 3, 4)}


def compact(raw: np.ndarray) -> np.ndarray:
    """``raw`` as uint8 when that is lossless (an 8-bit frame read as k/255: a quarter of the memory), else itself."""
    q = np.rint(raw * np.float32(255)).clip(0, 255).astype(np.uint8)
    return q if np.array_equal(q.astype(np.float32) / np.float32(255), raw) else raw
