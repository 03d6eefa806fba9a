"""Clip restoration: remove the tilt that a single frame cannot see by registering the frames of a sliding window to
a common reference, fusing them and deblurring the result (docs/clips.md).

For output frame t, the window W(t) holds the ``temporal`` frames around t (shifted inward at the clip's ends).
Each frame i is registered to a reference of its own window, in ``passes`` rounds:

1. reference R⁰_i = mean of the raw frames of W(i) (the temporal mean: geometrically the mean tilt, blurred);
   global shift of frame i against it (phase correlation: camera shake);
2. round k: dense backward flow of frame i onto R^(k−1)_i (OpenCV DIS, started from the previous round),
   frame i unwarped; R^k_i = mean of the unwarped frames of W(i) (sharper, same geometry);
3. output t = fusion of the last round's unwarped frames of W(t) (mean; robust: each pixel weighted by its
   agreement with the reference; fba: Fourier burst accumulation, restore/fusion.py); where the frame's own
   residual stays high (a moving object) the single frame is used instead (no ghost); then deblurred (none, a
   physics Wiener filter, or a model).

Memory holds about 2·temporal·passes frames whatever the clip's length (a stream). Assumes a static scene seen by a
static or slowly moving camera; moving objects fall back to the single frame (not restored).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from d2turb.defaults import CLIP_FUSIONS, DEFAULT_FUSION
from d2turb.errors import D2TurbError
from d2turb.registration import DenseFlow, check_registrable, global_shift_px, remap, shift_flow, to_gray_u8, to_hwc
from d2turb.restore.fusion import SharpestFusion, coarse_grey, fourier_burst_accumulation, sharp_coefficients
from d2turb.sim.otf import image_otf, pixel_frequency_grid
from d2turb.sim.params import MAX_DR0
from d2turb.sim.tilt import dr0_from_tilt_variance

FUSIONS = CLIP_FUSIONS
DEFAULT_TEMPORAL = 24
# Laplacian prior weight of the physics deblur: BALANCE_AT_2 · (D/r0 / 2)^(5/3). What limits the deconvolution of a
# fused frame is the residual misregistration, whose variance scales like the tilt variance, ∝ (D/r0)^(5/3)
# (docs/physics.md §2); BALANCE_AT_2 was chosen on the validation clips (docs/clips.md).
BALANCE_AT_2 = 0.002


def default_balance(dr0: float) -> float:
    return BALANCE_AT_2 * (dr0 / 2.0) ** (5 / 3)


# The physics deblur after the sharpest fusion: each coefficient comes from the frame that kept it best, so what is
# left is the blur of a weaker turbulence than the mean short-exposure one: the Wiener filter uses the OTF at
# D/r0 × SHARPEST_DR0_SCALE (chosen on the validation clips, docs/clips.md).
SHARPEST_DR0_SCALE = 0.3  # 0.6 / 0.5 / 0.4 / 0.3: 0.3 best in every bin (docs/clips.md), still below the mean + Wiener


def deblur_dr0(dr0: float, fusion: str) -> float:
    """The D/r0 at which the physics deblur of a clip fused by ``fusion`` models the fused frame's blur."""
    return dr0 * SHARPEST_DR0_SCALE if fusion == "sharpest" else dr0


# the last round's unwarped frames (what the fusion averages) are held as float16: half their memory, relative error
# 2^-11 (< 0.13 grey levels of 255), far below the fusion's noise. Raw frames and earlier rounds stay float32: they
# make the references that frames are registered onto, where a rounding that flips a grey level moves the flow
STORE_DTYPE = np.float16
_RESUM = 256  # running window sums are recomputed from scratch after this many updates (float32 drift)
_FALLBACK_BOX = 15  # px: residuals are averaged over this box before the moving-object test
_FALLBACK_LOW, _FALLBACK_HIGH = 3.0, 6.0  # in units of the frame's robust residual scale: blend from → to


@dataclass
class ClipFrame:
    """One restored frame: ``restored`` (deblurred fusion), ``fused`` (before deblurring) (3,H,W) float32 tensors
    in [0,1]; ``bwd_flow_px`` (2,H,W) float32 maps the input frame onto the restored geometry,
    ``frame(x + bwd_flow_px(x)) ≈ fused(x)``; ``fallback`` (H,W) in [0,1]: share of the single frame (1 = moving)."""

    index: int
    restored: torch.Tensor
    fused: torch.Tensor
    bwd_flow_px: torch.Tensor
    fallback: torch.Tensor


def window_start(index: int, temporal: int, length: int | None) -> int:
    """First frame of W(index): centred, shifted inward at the clip's ends (``length`` None: end not known yet)."""
    lo = max(0, index - temporal // 2)
    if length is not None:
        lo = min(lo, max(0, length - temporal))
    return lo


def laplacian_power(height: int, width: int) -> torch.Tensor:
    """|L(f)|² of the 5-point discrete Laplacian on the rfft2 grid: the Wiener filter's smoothness prior (natural
    images have a spectrum falling like 1/f², so noise amplification is penalised most where signal is weakest)."""
    fy = torch.fft.fftfreq(height, dtype=torch.float64)[:, None]
    fx = torch.fft.rfftfreq(width, dtype=torch.float64)[None, :]
    return (4 - 2 * torch.cos(2 * math.pi * fx) - 2 * torch.cos(2 * math.pi * fy)) ** 2


def _smooth_size(n: int) -> int:
    """The smallest 2·3·5-smooth integer >= n (sizes the FFT handles fast)."""
    while True:
        m = n
        for p in (2, 3, 5):
            while m % p == 0:
                m //= p
        if m == 1:
            return n
        n += 1


def wiener_padding(height: int, width: int) -> tuple[int, int, int, int]:
    """Mirror padding (top, bottom, left, right) that keeps the FFT's periodic wrap-around away from the image: an
    eighth of the shorter side (at least 8 px), then up to an FFT-friendly size."""
    pad = max(8, min(height, width) // 8)
    top, left = min(height - 1, pad), min(width - 1, pad)
    bottom = min(height - 1, _smooth_size(height + 2 * top) - height - top)
    right = min(width - 1, _smooth_size(width + 2 * left) - width - left)
    return top, bottom, left, right


def wiener_deconvolve(image: torch.Tensor, gain: torch.Tensor) -> torch.Tensor:
    """Apply a Wiener filter's gain G = H / (H² + balance·|L|²) (see :func:`wiener_gain`) to the rfft2 of the
    mirror-padded image (the form of scikit-image's ``restoration.wiener``, here with the OTF given directly).

    Shape:
        image: (C, H, W); gain: the rfft2 grid of the image padded by ``wiener_padding(H, W)``.
    """
    top, bottom, left, right = wiener_padding(*image.shape[-2:])
    h, w = image.shape[-2:]
    out = torch.empty(image.shape, dtype=torch.float32)
    for c in range(image.shape[0]):  # a channel at a time: a third of the FFT buffers (1080p: ~120 MB less)
        padded = torch.nn.functional.pad(image[None, c : c + 1].float(), (left, right, top, bottom), mode="reflect")
        full = torch.fft.irfft2(torch.fft.rfft2(padded[0, 0]) * gain, s=padded.shape[-2:])
        out[c] = full[top : top + h, left : left + w]
    return out.clamp_(0, 1)


def wiener_gain(otf: torch.Tensor, balance: float, shape: tuple[int, int]) -> torch.Tensor:
    """G = H / (H² + balance·|L|²) on the rfft2 grid of ``shape``, float32."""
    return (otf / (otf * otf + balance * laplacian_power(*shape))).float()


class PhysicsDeblur:
    """Wiener deconvolution with the short-exposure (tilt-removed) turbulence OTF at ``dr0`` (docs/physics.md §4).

    With depth modulation M (paper Eq. 4: blurred = M·(I ⊛ PSF) + (1 − M)·I), the effective OTF is
    M·T·H + (1 − M); ``modulation`` is the image's mean M (1: the whole path at ``dr0``). A fused frame is also
    blurred by what the registration left: each frame of the window is off by a random residual shift, so their mean
    is the frame convolved with the shifts' distribution, a Gaussian of ``jitter_px`` (σ per axis, px), whose OTF
    exp(−2π²σ²|f|²) multiplies the short-exposure one.

    Args:
        dr0: D/r0 of the path; lambda_over_d_px: λ/(D·ifov), the diffraction angle in pixels (2 = Nyquist).
        balance: weight of the Laplacian smoothness prior (regularisation); default ``default_balance(dr0)``.
        modulation: mean depth modulation M in (0, 1].
        jitter_px: σ per axis of the residual registration error of the frames fused (0: a single frame).
    """

    def __init__(
        self,
        dr0: float,
        lambda_over_d_px: float = 2.0,
        balance: float | None = None,
        modulation: float = 1.0,
        alpha: float = 1.0,
        jitter_px: float = 0.0,
    ):
        if not isinstance(dr0, (int, float)) or not math.isfinite(dr0) or not 0 < dr0 <= MAX_DR0:
            raise D2TurbError(f"--dr0 must be in (0, {MAX_DR0:g}], got {dr0!r}")
        balance = default_balance(dr0) if balance is None else balance
        if not math.isfinite(balance) or balance <= 0:
            raise D2TurbError(f"the Wiener balance must be positive and finite, got {balance!r}")
        if not math.isfinite(lambda_over_d_px) or not 0.05 <= lambda_over_d_px <= 50:
            raise D2TurbError(f"λ/(D·ifov) = {lambda_over_d_px:.3g} px is outside [0.05, 50] (check the optics)")
        if not 0 < modulation <= 1:
            raise D2TurbError(f"modulation must be in (0, 1], got {modulation!r}")
        if not math.isfinite(jitter_px) or not 0 <= jitter_px <= 20:
            raise D2TurbError(f"the residual registration jitter must be in [0, 20] px, got {jitter_px!r}")
        self.dr0, self.lambda_over_d_px, self.balance = float(dr0), float(lambda_over_d_px), float(balance)
        self.modulation, self.alpha, self.jitter_px = float(modulation), float(alpha), float(jitter_px)
        self._gain: dict[tuple[int, int], torch.Tensor] = {}  # per image size

    def otf(self, height: int, width: int) -> torch.Tensor:
        """The effective OTF on the rfft2 grid of a (height, width) image after ``wiener_padding`` (float64)."""
        top, bottom, left, right = wiener_padding(height, width)
        shape = (height + top + bottom, width + left + right)
        otf = self.modulation * image_otf(*shape, self.dr0, self.lambda_over_d_px, self.alpha) + (1 - self.modulation)
        if self.jitter_px > 0:
            otf = otf * torch.exp(-2 * math.pi**2 * self.jitter_px**2 * pixel_frequency_grid(*shape) ** 2)
        return otf

    def __call__(self, image: torch.Tensor) -> torch.Tensor:
        """Shape: (C, H, W) → (C, H, W), float32 in [0, 1]."""
        size = tuple(image.shape[-2:])
        if size not in self._gain:
            top, bottom, left, right = wiener_padding(*size)
            shape = (size[0] + top + bottom, size[1] + left + right)
            self._gain[size] = wiener_gain(self.otf(*size), self.balance, shape)
        return wiener_deconvolve(image, self._gain[size])


@dataclass
class _Frame:
    raw: np.ndarray  # (H,W,C) uint8 when that holds the float32 frame exactly (8-bit input), else float32; see .image
    gray: np.ndarray  # (H,W) uint8
    flows: list = field(default_factory=list)  # per round: (H,W,2) backward flow onto that round's reference
    warped: list = field(default_factory=list)  # per round: the frame unwarped, (H,W,C) float32 (last: STORE_DTYPE)
    sharp: object = None  # fusion "sharpest": the last round's SharpCoefficients (as long as that round's image)
    coarse: object = None  # fusion "sharpest": coarse grey of the image the last round's reference averages

    def image(self) -> np.ndarray:
        """The frame as (H,W,C) float32 in [0,1] (bit-identical to the frame given: k/255 in float32)."""
        return self.raw.astype(np.float32) / np.float32(255) if self.raw.dtype == np.uint8 else self.raw


def _compact(raw: np.ndarray) -> np.ndarray:
    """``raw`` as uint8 when that is lossless (an 8-bit frame read as k/255: a quarter of the memory), else itself."""
    q = np.rint(raw * np.float32(255)).clip(0, 255).astype(np.uint8)
    return q if np.array_equal(q.astype(np.float32) / np.float32(255), raw) else raw


class ClipRestorer:
    """Restore a clip of a static scene by registration, fusion and deblurring over a sliding window.

    Args:
        temporal: frames per window (≥ 2).
        passes: registration rounds (≥ 1); each refines the reference from the previous round's fusion.
        fusion: "mean", "robust" (pixels weighted by their agreement with the reference) or "fba" (Fourier burst
            accumulation: each frequency mostly from the frames that kept it best, ``restore/fusion.py``).
        deblur: "none", a :class:`PhysicsDeblur`, or any callable (3,H,W) → (3,H,W) (e.g. a model's ``restore``).
        preset: registration accuracy, a key of ``d2turb.registration.DIS_PRESETS`` (default "fast": the flow at
            half resolution, as good as "medium" after fusion on the validation clips and 4× faster; docs/clips.md).
        stabilise: remove a global shift per frame (camera shake) before the dense registration.
        fallback: use the single frame where its residual against the fusion stays high (moving objects).
    """

    def __init__(
        self,
        temporal: int = DEFAULT_TEMPORAL,
        passes: int = 2,
        fusion: str = DEFAULT_FUSION,
        deblur="none",
        preset: str = "fast",
        stabilise: bool = True,
        fallback: bool = True,
    ):
        if not isinstance(temporal, int) or isinstance(temporal, bool) or temporal < 2:
            raise D2TurbError(f"--temporal must be an integer >= 2, got {temporal!r}")
        if not isinstance(passes, int) or isinstance(passes, bool) or passes < 1:
            raise D2TurbError(f"passes must be an integer >= 1, got {passes!r}")
        if fusion not in FUSIONS:
            raise D2TurbError(f"unknown fusion {fusion!r}; choose one of {', '.join(FUSIONS)}")
        if not (deblur == "none" or callable(deblur)):
            raise D2TurbError(f"deblur must be 'none' or a callable, got {deblur!r}")
        self.temporal, self.passes, self.fusion = temporal, passes, fusion
        self.deblur = None if deblur == "none" else deblur
        self.stabilise, self.fallback = stabilise, fallback
        DenseFlow(preset)  # an unknown preset is an error now, not at the first frame
        self.preset = preset
        self.flow = None  # a fresh solver per clip

    # -- the stream ------------------------------------------------------------------------------------------------
    def restore(self, frames: Iterable) -> Iterator[ClipFrame]:
        """Restored frames in order, one per input frame ((3,H,W) tensors or (H,W,3) arrays in [0,1]), computed
        with a bounded lookahead. Raises ``D2TurbError`` for frames of different sizes or a clip of < 2 frames."""
        source = iter(frames)
        passes = self.passes
        buf: dict[int, _Frame] = {}
        length = None
        shape = None
        done = [0] * (passes + 1)  # done[k]: frames whose round k is computed (k = 0: read); next output = done[0]
        emitted = 0
        self.flow = None
        self._sums: dict[int, tuple] = {}  # level → (lo, hi, running sum, updates since recomputed)
        self._sharp = SharpestFusion()  # the window's current choice (fusion "sharpest")
        self.buffered = 0  # frame images held in memory (bounded by the window, not by the clip's length)
        while emitted < (length if length is not None else math.inf):
            progressed = False
            if length is None:
                item = next(source, None)
                if item is None:
                    length = done[0]
                    if length < 2:
                        raise D2TurbError(f"a clip needs at least 2 frames, got {length}")
                else:
                    raw = to_hwc(item)
                    if shape is None:
                        check_registrable(*raw.shape[:2])
                        shape = raw.shape
                    elif raw.shape != shape:
                        raise D2TurbError(
                            f"frame {done[0]} is {raw.shape[1]}x{raw.shape[0]}, the clip's first is "
                            f"{shape[1]}x{shape[0]}: all frames of a clip must have one size"
                        )
                    if self.flow is None:
                        self.flow = DenseFlow(self.preset)
                    buf[done[0]] = _Frame(_compact(raw), to_gray_u8(raw))
                    done[0] += 1
                progressed = True
            total = length if length is not None else done[0]
            for k in range(1, passes + 1):  # round k of frame i needs round k-1 of W(i)
                while done[k] < total and self._window_ready(done[k], k - 1, done, length):
                    self._register(buf, done[k], k, length)
                    done[k] += 1
                    progressed = True
            while emitted < done[passes] and self._window_ready(emitted, passes, done, length):
                yield self._output(buf, emitted, length)
                emitted += 1
                progressed = True
            self._release(buf, done, emitted, length)
            if not progressed and length is not None:
                raise RuntimeError("clip restoration made no progress")  # pragma: no cover - a logic error

    def _release(self, buf: dict, done: list, emitted: int, length: int | None) -> None:
        """Free each frame's images once nothing left to compute reads them: level L's image (0: the raw frame, k:
        round k's unwarped frame) of frame j is read by the references of round L + 1 (windows from
        W(done[L+1]) on) and by the running sum of level L; the raw frame also by its own registration rounds and
        by the output's fallback; the last round by the outputs' fusion. Frames with nothing left are dropped."""
        n, passes = self.temporal, self.passes
        guard = done[0] - n if length is None else math.inf  # the end may still shift the last windows back
        readers = []
        for level in range(passes + 1):
            first = window_start(emitted if level == passes else done[level + 1], n, length)
            if level in self._sums:
                first = min(first, self._sums[level][0])
            if level == 0:
                first = min(first, emitted, done[passes])
            readers.append(min(first, guard))
        for j in [j for j in buf if j < max(readers)]:
            frame = buf[j]
            if j < readers[0]:
                frame.raw = None
            for level in range(1, passes + 1):
                if j < readers[level] and len(frame.warped) >= level:
                    frame.warped[level - 1] = None
                    if level == passes:
                        frame.sharp = None
            if frame.raw is None and len(frame.warped) == passes and all(w is None for w in frame.warped):
                del buf[j]
        self.buffered = sum((f.raw is not None) + sum(w is not None for w in f.warped) for f in buf.values())

    def _window_ready(self, index: int, level: int, done: list, length: int | None) -> bool:
        lo = window_start(index, self.temporal, length)
        hi = lo + self.temporal if length is None else min(length, lo + self.temporal)
        return done[level] >= hi

    def _window(self, buf: dict, index: int, length: int | None) -> list[int]:
        lo = window_start(index, self.temporal, length)
        hi = lo + self.temporal if length is None else min(length, lo + self.temporal)
        return list(range(lo, hi))

    def _reference(self, buf: dict, index: int, level: int, length: int | None) -> np.ndarray:
        """Mean of level ``level`` (0: raw frames, k: round k's unwarped frames) over W(index), from a running sum
        updated by the frames entering and leaving the window (recomputed every ``_RESUM`` updates)."""
        members = self._window(buf, index, length)
        lo, hi = members[0], members[-1] + 1
        cached = self._sums.get(level)

        def image(j):
            return buf[j].image() if level == 0 else buf[j].warped[level - 1]

        if cached is None or cached[3] >= _RESUM or cached[0] > lo or cached[1] > hi or cached[1] <= lo:
            total = image(members[0]).astype(np.float32)  # summed in place: no stack of the window in memory
            for j in members[1:]:
                total += image(j)
            count = 0
        else:
            c_lo, c_hi, total, count = cached
            for j in range(c_hi, hi):
                total += image(j)
            for j in range(c_lo, lo):
                total -= image(j)
            count += 1
        self._sums[level] = (lo, hi, total, count)
        return total / np.float32(hi - lo)

    def _register(self, buf: dict, index: int, k: int, length: int | None) -> None:
        frame = buf[index]
        ref = self._reference(buf, index, k - 1, length)
        ref_gray = to_gray_u8(ref)
        if k == 1:
            init = shift_flow(frame.gray.shape, *global_shift_px(ref_gray, frame.gray)) if self.stabilise else None
        else:
            init = frame.flows[-1]
        flow = self.flow(ref_gray, frame.gray, init)
        frame.flows = [flow]  # the last round's flow: the output's and the next round's start
        warped = remap(frame.image(), flow)
        frame.warped.append(warped.astype(STORE_DTYPE) if k == self.passes else warped)
        if k == self.passes and self.fusion == "sharpest":  # outliers against the median of the window's frames
            members = [buf[j] for j in self._window(buf, index, length)]
            for f in members:
                if f.coarse is None:
                    f.coarse = coarse_grey(f.image() if k == 1 else f.warped[k - 2])
            median = np.median(np.stack([f.coarse for f in members]), axis=0)
            frame.sharp = sharp_coefficients(warped, median)

    def _output(self, buf: dict, index: int, length: int | None) -> ClipFrame:
        fused = self._reference(buf, index, self.passes, length)
        if self.fusion == "robust":
            fused = self._robust([buf[j].warped[-1] for j in self._window(buf, index, length)], fused)
        elif self.fusion == "fba":
            fused = fourier_burst_accumulation([buf[j].warped[-1] for j in self._window(buf, index, length)])
        elif self.fusion == "sharpest":
            fused = self._sharp.fuse({j: buf[j].sharp for j in self._window(buf, index, length)})
        frame = buf[index]
        blend = np.zeros(fused.shape[:2], dtype=np.float32)
        if self.fallback:
            blend = self._fallback_share(frame.warped[-1], fused)
            if blend.any():
                fused = fused + blend[..., None] * (frame.image() - fused)
        fused_t = torch.from_numpy(np.ascontiguousarray(np.clip(fused, 0, 1).transpose(2, 0, 1)))
        restored = fused_t if self.deblur is None else self.deblur(fused_t)
        flow = torch.from_numpy(np.ascontiguousarray(frame.flows[-1].transpose(2, 0, 1)))
        return ClipFrame(index, restored, fused_t, flow, torch.from_numpy(blend))

    @staticmethod
    def _robust(stack: list[np.ndarray], mean: np.ndarray) -> np.ndarray:
        """Per-pixel weights 1/(1 + (r/τ)²) of each frame's residual r against the mean, τ its robust scale."""
        num = np.zeros_like(mean)
        den = np.zeros(mean.shape[:2] + (1,), dtype=np.float32)
        for img in stack:
            r = np.abs(img - mean).mean(axis=2, keepdims=True)
            tau = max(1.4826 * float(np.median(r)), 1e-3)
            w = 1.0 / (1.0 + (r / (2.0 * tau)) ** 2)
            num += w * img
            den += w
        return num / den

    @staticmethod
    def _fallback_share(warped: np.ndarray, fused: np.ndarray) -> np.ndarray:
        """Share of the single frame per pixel: 0 where the registered frame agrees with the fusion within a few
        robust scales of its residual (box-averaged), rising to 1 where it stays far above (a moving object)."""
        r = cv2.blur(np.abs(warped - fused).mean(axis=2), (_FALLBACK_BOX, _FALLBACK_BOX))
        scale = max(1.4826 * float(np.median(r)), 1e-3)
        z = (r / scale - _FALLBACK_LOW) / (_FALLBACK_HIGH - _FALLBACK_LOW)
        share = np.clip(z, 0, 1).astype(np.float32)
        return cv2.dilate(share, np.ones((_FALLBACK_BOX, _FALLBACK_BOX), np.uint8)) if share.any() else share


# Share of the tilt variance (Z-tilt per axis, docs/physics.md §2) that the registered flows of a window of
# REGISTRATION_WINDOW frames carry (each frame's mean shift removed): the registration sees only the part that
# changes within the window, and DIS smooths it. Median over the 24 validation clips (docs/clips.md).
OBSERVED_TILT_SHARE = 0.13
REGISTRATION_WINDOW = 32


def flow_variance_px2(bwd_flow_px: torch.Tensor) -> float:
    """Per-axis variance (px²) of one (2, H, W) flow about its own mean (the frame's global shift, camera shake)."""
    f = bwd_flow_px.double()
    return float(((f - f.mean((1, 2), keepdim=True)) ** 2).mean()) / 2


def registration_tilt_variance(frames: Iterable, temporal: int = REGISTRATION_WINDOW, preset: str = "fast") -> float:
    """Per-axis variance (px²) of the backward flows that register each frame of ``frames`` onto its window's
    fusion (:class:`ClipRestorer`, no deblur), each frame's mean shift (camera shake) removed, averaged over the
    frames."""
    total, count = 0.0, 0
    for out in ClipRestorer(temporal=temporal, preset=preset, fallback=False).restore(frames):
        total += flow_variance_px2(out.bwd_flow_px)
        count += 1
    return total / max(count, 1)


def registration_dr0(frames: Iterable, lambda_over_d_px: float = 2.0, preset: str = "fast") -> float:
    """D/r0 from the clip's own registration, for a clip that ``d2turb measure`` cannot measure: the tilt variance
    is the registered flows' variance over ``OBSERVED_TILT_SHARE`` (calibrated on the simulated validation clips at a
    window of ``REGISTRATION_WINDOW`` frames; a rough estimate: 0.10–0.15 there, unknown on real footage), inverted by
    the Z-tilt law σ² = 0.1816 (λ/D)² (D/r0)^(5/3) with λ/D in pixels. Clipped to [0.05, MAX_DR0]."""
    var = registration_tilt_variance(frames, REGISTRATION_WINDOW, preset) / OBSERVED_TILT_SHARE
    dr0 = float(dr0_from_tilt_variance(var, 1.0, lambda_over_d_px, 1.0))  # only λ/(D·ifov) matters
    return min(max(dr0, 0.05), MAX_DR0)


def restore_clip(frames: Iterable, **kwargs) -> Iterator[ClipFrame]:
    """``ClipRestorer(**kwargs).restore(frames)``: see :class:`ClipRestorer`."""
    return ClipRestorer(**kwargs).restore(frames)


__all__ = [
    "ClipRestorer",
    "ClipFrame",
    "PhysicsDeblur",
    "flow_variance_px2",
    "registration_dr0",
    "registration_tilt_variance",
    "restore_clip",
    "window_start",
    "wiener_deconvolve",
]
