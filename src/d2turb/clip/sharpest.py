"""Sharpest-coefficient fusion (``--fusion sharpest``), streamed over a sliding window.

Per level of a Laplacian pyramid (Burt & Adelson 1983) each detail coefficient of the output is the registered frame's
coefficient with the largest colour amplitude √(Σ_c d_c²) in the window (one choice for all channels), the rule of
wavelet-domain fusion for turbulence (Anantrasirichai et al., IEEE TIP 2013, with a DT-CWT); the coarsest level
(1/2^L resolution) is the inliers' mean. Outliers: each frame is compared, at that coarse resolution in grey, with
the per-pixel median of its window's frames (a robust reference: a square that is in one frame only is not in it);
where the frame stays far above its robust residual scale (a moving object, a registration failure) its
coefficients are never chosen and its low-pass is left out of the mean; where fewer than 3/4 of the window's
frames are inliers (a moving object crosses the place), and where the chosen amplitude exceeds 3 × the window's
mean amplitude (an edge that few frames hold: misregistered, a moving object's), the mean's coefficient is kept
(the peer's rule is max-of-inliers, below 2 × the median amplitude; a mean can be streamed). Streamed: each
frame's pyramid is computed once, when it is registered, and kept while a window holds it, in fixed point (int16 of
1/FIXED_ONE: 1/64 of a grey level, about float16's step on a detail of 30 grey levels; OpenCV's pyramids and numpy's
casts run 3-4x faster on int16 than on float32 and float16); the window's
choice is updated incrementally (a frame entering is compared everywhere, a frame leaving makes only the pixels it
held be re-chosen among the others), so the result equals the direct argmax; the amplitudes' sum is a running sum.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from d2turb.clip.registration import to_hwc
from d2turb.errors import D2TurbError

SHARP_LEVELS = 3  # detail levels; 3–5 within 0.05 dB on the validation clips (docs/clips.md)
_GATE_LOW, _GATE_HIGH = 3.0, 6.0  # robust scales of the frame's coarse residual: full weight → ruled out
_OUTSTANDING = 3.0  # a choice above this × the window's mean amplitude is replaced by the mean's coefficient
_SHARE_LOW, _SHARE_HIGH = 0.5, 0.75  # inlier share of the window: the mean's coefficients → the choice
_GATE_FLOOR = 0.01  # least robust scale (2.5 grey levels): frames that differ only by their blur are all inliers
FIXED_ONE = 255 * 64  # the pyramids' fixed point: an 8-bit frame's value v is v << 6; |values| < 2 fit in int16
# (details of frames in [0, 1] stay within ±FIXED_ONE; OpenCV's int16 arithmetic saturates beyond)


def laplacian_pyramid(image: np.ndarray, levels: int) -> list[np.ndarray]:
    """``levels`` detail images (fine to coarse) and the low-pass residual, float32 (int16 kept: OpenCV rounds each
    level); exact inverse :func:`collapse_pyramid`."""
    out, cur = [], image if image.dtype == np.int16 else np.asarray(image, dtype=np.float32)
    for _ in range(levels):
        down = cv2.pyrDown(cur)
        out.append(cv2.subtract(cur, cv2.pyrUp(down, dstsize=(cur.shape[1], cur.shape[0]))).reshape(cur.shape))
        cur = down.reshape(down.shape[:2] + cur.shape[2:])
    out.append(cur)
    return out


def _rows(image: np.ndarray) -> np.ndarray:
    """A C-contiguous (h,w,C) array as h·w elements of C values each (one opaque item: numpy's indexed copies move
    whole pixels about twice as fast as rows of a 2-D view)."""
    return image.reshape(-1).view(np.dtype((np.void, image.itemsize * image.shape[-1])))


def collapse_pyramid(pyramid: list[np.ndarray], consume: bool = False) -> np.ndarray:
    """The image of :func:`laplacian_pyramid`'s ``pyramid``; ``consume``: its details are the caller's to give up
    (each level is summed into its own array: a frame-sized temporary fewer)."""
    cur = pyramid[-1]
    for detail in reversed(pyramid[:-1]):
        up = cv2.pyrUp(cur, dstsize=(detail.shape[1], detail.shape[0])).reshape(detail.shape)
        cur = cv2.add(up, detail, dst=detail) if consume else cv2.add(up, detail)
        cur = cur.reshape(detail.shape)  # OpenCV drops a single channel's axis
    return cur


def coarse_grey(image: np.ndarray, levels: int = SHARP_LEVELS) -> np.ndarray:
    """The grey mean over channels of ``image`` (H,W,C) area-averaged to the size of its pyramid's low-pass."""
    h, w = image.shape[:2]
    for _ in range(levels):
        h, w = (h + 1) // 2, (w + 1) // 2
    small = cv2.resize(np.asarray(image, np.float32), (w, h), interpolation=cv2.INTER_AREA)
    return small.reshape(h, w, -1).mean(axis=2)


def outlier_gate(coarse: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(h,w) float32 in [0,1], from a frame's and its robust reference's :func:`coarse_grey`: 1 where the frame
    agrees within a few robust scales of its residual (at least ``_GATE_FLOOR``), 0 where it stays far above (3 × 3
    coarse pixels averaged)."""
    r = cv2.blur(np.abs(coarse - reference), (3, 3))
    scale = max(1.4826 * float(np.median(r)), _GATE_FLOOR)
    return np.clip((_GATE_HIGH - r / scale) / (_GATE_HIGH - _GATE_LOW), 0, 1).astype(np.float32)


@dataclass
class SharpCoefficients:
    """One registered frame's selection data, in units of 1/FIXED_ONE: detail coefficients (fine to coarse, (h,w,C)
    int16), their selection amplitude ((h,w) uint16: colour amplitude × inlier gate, rounded), the low-pass (h,w,C)
    float32; and its inlier gate (h,w) float32."""

    details: list
    amplitude: list
    lowpass: np.ndarray
    gate: np.ndarray


def to_fixed(image: np.ndarray) -> np.ndarray:
    """An image in [0, 1] (8-bit as stored: uint8; or float) as int16 in units of 1/FIXED_ONE (NaN as 0: a cast
    of NaN to an integer is undefined)."""
    if image.dtype == np.uint8:
        return np.left_shift(image.astype(np.int16), 6)  # v/255 · 255·64, exactly
    finite = np.nan_to_num(np.asarray(image, np.float32), nan=0.0)
    return np.rint(np.clip(finite, -2.0, 2.0) * FIXED_ONE).astype(np.int16)


def sharp_coefficients(warped: np.ndarray, reference: np.ndarray, levels: int = SHARP_LEVELS) -> SharpCoefficients:
    """The selection data of one registered frame ``warped`` (H,W,C) in [0, 1] (uint8 as stored, or float);
    ``reference``: the per-pixel median of the :func:`coarse_grey` of its window's frames."""
    pyramid = laplacian_pyramid(to_fixed(warped), levels)
    gate = outlier_gate(coarse_grey(to_hwc(warped), levels), reference)
    amplitude = []
    for d in pyramid[:-1]:
        g = cv2.resize(gate, (d.shape[1], d.shape[0]), interpolation=cv2.INTER_LINEAR)
        # √(Σ_c d_c²) × gate, rounded (< 2·√3·FIXED_ONE: fits uint16); OpenCV's channel sum: 5× numpy's .sum(axis=2);
        # the squares straight from int16 to float32 (one rounding, as float32's product), the rest in place
        power = cv2.transform(cv2.multiply(d, d, dtype=cv2.CV_32F), np.ones((1, d.shape[2]), np.float32))
        power = cv2.sqrt(power, dst=power).reshape(g.shape)
        power = np.rint(cv2.multiply(power, g, dst=power), out=power)
        amplitude.append(power.astype(np.uint16))
    return SharpCoefficients(pyramid[:-1], amplitude, pyramid[-1].astype(np.float32), gate)


class SharpestFusion:
    """Streamed sharpest-coefficient fusion over a sliding window (module comment above). Call :meth:`fuse` once
    per output with the window's frames; memory: one pyramid per frame held plus the current choice."""

    def __init__(self):
        self.members: set[int] = set()
        # per level: [amplitude (h,w) int32 (-1: none yet), coefficient (h,w,C) int16, frame index (h,w) int32]
        self.best = None
        self.amp_sum = None  # per level: Σ over the members of their amplitudes (h,w) f32
        self.amps: dict[int, list] = {}  # the members' amplitudes (subtracted when they leave)
        self._scratch = None  # per level: arrays reused from output to output (made with best)

    def fuse(self, window: dict[int, SharpCoefficients], mean: np.ndarray) -> np.ndarray:
        """Fusion of the frames ``window`` (index → coefficients); where no frame may be chosen, the coefficient of
        ``mean``, the window's mean frame (H,W,C) in [0, 1] (a pyramid is linear: its coefficients are the frames'
        mean coefficients, to rounding)."""
        if not window:
            raise D2TurbError("sharpest fusion needs at least one frame")
        ids = sorted(window)
        levels = len(window[ids[0]].details)
        leaving = self.members - set(ids)
        if self.best is None or len(leaving) >= len(ids) or len(self.best) != levels:
            self.best, self.members, leaving = None, set(), set()
        if self.best is None:
            self.amp_sum = [np.zeros(d.shape[:2], np.float32) for d in window[ids[0]].details]
            self.amps = {}
            self.best = [
                [np.full(d.shape[:2], -1, np.int32), np.zeros(d.shape, np.int16), np.full(d.shape[:2], -1, np.int32)]
                for d in window[ids[0]].details
            ]
            # per level, reused from output to output (fresh frame-sized arrays cost more in page faults than the
            # arithmetic): the outstanding threshold (h,w) f32 and two (h,w) masks
            self._scratch = [
                (np.empty(d.shape[:2], np.float32), np.empty(d.shape[:2], bool), np.empty(d.shape[:2], bool))
                for d in window[ids[0]].details
            ]
        staying = [j for j in ids if j in self.members]
        for j in leaving:
            for total, a in zip(self.amp_sum, self.amps.pop(j)):
                total -= a
        for j in ids:
            if j not in self.members:
                self.amps[j] = window[j].amplitude
                for total, a in zip(self.amp_sum, window[j].amplitude):
                    total += a
        for level, (amp, coef, who) in enumerate(self.best):
            a_flat, w_flat, c_rows = amp.reshape(-1), who.reshape(-1), _rows(coef)
            if leaving:  # re-choose, among the frames that stay, the pixels a leaving frame held
                held = who == next(iter(leaving)) if len(leaving) == 1 else np.isin(who, list(leaving))
                idx = np.flatnonzero(held)
                if staying:  # the first largest in index order, as a strict > over the sorted frames would keep
                    cand = np.stack([np.take(window[j].amplitude[level].reshape(-1), idx) for j in staying])
                    pick = cand.argmax(axis=0)
                    a_flat[idx] = cand[pick, np.arange(idx.size)]
                    w_flat[idx] = np.asarray(staying)[pick]
                    for k, j in enumerate(staying):
                        sel = idx[pick == k]
                        c_rows[sel] = np.take(_rows(window[j].details[level]), sel)
                else:
                    a_flat[idx], w_flat[idx] = -1, -1
            for j in ids:
                if j in self.members:
                    continue
                a, d = window[j].amplitude[level], window[j].details[level]
                mask = a > amp
                if np.count_nonzero(mask) > mask.size // 8:  # a window filling up: masked copies
                    np.copyto(amp, a, where=mask)
                    np.copyto(who, j, where=mask)
                    np.copyto(coef, d, where=mask[..., None])
                    continue
                better = np.flatnonzero(mask)  # a few percent of the pixels: indexed copies, not masked ones
                a_flat[better] = np.take(a.reshape(-1), better)
                w_flat[better] = j
                c_rows[better] = np.take(_rows(d), better)
        self.members = set(ids)
        # the mean's pyramid, in fixed point as the frames' (OpenCV's pyramids: 3-4x faster on int16 than float32)
        flat = np.ascontiguousarray(mean, np.float32).reshape(mean.shape[0], -1)  # one channel: a scalar scales all
        pyramid = laplacian_pyramid(cv2.multiply(flat, float(FIXED_ONE), dtype=cv2.CV_16S).reshape(mean.shape), levels)
        pyramid[-1] = pyramid[-1].astype(np.float32)
        num = np.zeros_like(pyramid[-1])
        den = np.zeros(num.shape[:2] + (1,), np.float32)
        for j in ids:  # the inliers' mean of the low-passes (1/4^L of the pixels: computed afresh)
            num += window[j].gate[..., None] * window[j].lowpass
            den += window[j].gate[..., None]
        # where too few frames of the window agree (a moving object crosses it) the choice is noise: the mean's
        share = np.clip((den[..., 0] / len(ids) - _SHARE_LOW) / (_SHARE_HIGH - _SHARE_LOW), 0, 1)
        pyramid[-1] = pyramid[-1] + share[..., None] * (num / np.maximum(den, 1e-3) - pyramid[-1])
        for level, ((amp, coef, _), (limit, none, out)) in enumerate(zip(self.best, self._scratch)):
            s = cv2.resize(share, (coef.shape[1], coef.shape[0]), interpolation=cv2.INTER_LINEAR)
            # nothing to choose, or the choice stands out of the window (an edge in few frames: misregistered);
            # amplitudes are exact in float32 (< 2^24): compared there, not promoted to float64
            np.divide(np.multiply(self.amp_sum[level], np.float32(_OUTSTANDING), out=limit), len(ids), out=limit)
            np.greater(amp.astype(np.float32), limit, out=out)
            np.less_equal(amp, 0, out=none)
            s[np.logical_or(none, out, out=out)] = 0
            step = np.subtract(coef, pyramid[level], dtype=np.float32)  # mean + s·(choice − mean)
            step *= s.reshape(s.shape[:2] + (1,))
            pyramid[level] = np.add(step, pyramid[level], out=step)
        fused = collapse_pyramid(pyramid, consume=True)  # every level is this call's own float32 array
        return np.divide(fused, np.float32(FIXED_ONE), out=fused)


def robust_reference(stack: list[np.ndarray], levels: int = SHARP_LEVELS) -> np.ndarray:
    """The per-pixel median of the frames' :func:`coarse_grey` (a frame's reference for :func:`sharp_coefficients`)."""
    return np.median(np.stack([coarse_grey(f, levels) for f in stack]), axis=0)


def sharpest_fusion(stack: list[np.ndarray], levels: int = SHARP_LEVELS) -> np.ndarray:
    """Sharpest-coefficient fusion of one window of registered frames (H,W,C) at once. Returns (H,W,C) float32."""
    if not stack:
        raise D2TurbError("sharpest fusion needs at least one frame")
    frames = [np.asarray(s, dtype=np.float32) for s in stack]
    ref = robust_reference(frames, levels)
    coeffs = {i: sharp_coefficients(f, ref, levels) for i, f in enumerate(frames)}
    return SharpestFusion().fuse(coeffs, np.mean(frames, axis=0, dtype=np.float32))
