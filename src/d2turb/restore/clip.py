"""Clip restoration: remove the tilt that a single frame cannot see by registering the frames of a sliding window to
a common reference, fusing them and deblurring the result (docs/clips.md).

For output frame t, the window W(t) holds the ``temporal`` frames around t (shifted inward at the clip's ends).
Each frame i is registered to a reference of its own window, in ``passes`` rounds:

1. reference R⁰_i = mean of the raw frames of W(i) (the temporal mean: geometrically the mean tilt, blurred);
   global shift of frame i against it (phase correlation: camera shake);
2. round k: dense backward flow of frame i onto R^(k−1)_i (OpenCV DIS, started from the previous round),
   frame i unwarped; R^k_i = mean of the unwarped frames of W(i) (sharper, same geometry);
3. output t = fusion of the last round's unwarped frames of W(t) (mean, or robust: each pixel weighted by its
   agreement with the reference); where the frame's own residual stays high (a moving object) the single frame
   is used instead (no ghost); then deblurred (none, a physics Wiener filter, or a model).

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

from d2turb.errors import D2TurbError
from d2turb.registration import DenseFlow, global_shift_px, remap, shift_flow, to_gray_u8, to_hwc
from d2turb.sim.otf import image_otf
from d2turb.sim.params import MAX_DR0

FUSIONS = ("mean", "robust")
DEBLURS = ("none", "physics")  # or a model: weights name/path, or an nn.Module
DEFAULT_TEMPORAL = 24
# Laplacian prior weight of the physics deblur: BALANCE_AT_2 · (D/r0 / 2)^(5/3). What limits the deconvolution of a
# fused frame is the residual misregistration, whose variance scales like the tilt variance, ∝ (D/r0)^(5/3)
# (docs/physics.md §2); BALANCE_AT_2 was chosen on the validation clips (docs/clips.md).
BALANCE_AT_2 = 0.03


def default_balance(dr0: float) -> float:
    return BALANCE_AT_2 * (dr0 / 2.0) ** (5 / 3)


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


def wiener_padding(height: int, width: int) -> tuple[int, int]:
    """Mirror padding (rows, columns) that keeps the FFT's periodic wrap-around away from the image."""
    return min(height - 1, max(8, height // 4)), min(width - 1, max(8, width // 4))


def wiener_deconvolve(image: torch.Tensor, otf: torch.Tensor, balance: float) -> torch.Tensor:
    """Regularised Wiener filter X = H·Y / (H² + balance·|L|²) with a real OTF H on the rfft2 grid of the mirror-padded
    image (the form of scikit-image's ``restoration.wiener``, here with the OTF given directly).

    Shape:
        image: (C, H, W); otf: (H + 2·ph, (W + 2·pw) // 2 + 1) for ph, pw = ``wiener_padding(H, W)``.
    """
    ph, pw = wiener_padding(*image.shape[-2:])
    padded = torch.nn.functional.pad(image[None].double(), (pw, pw, ph, ph), mode="reflect")[0]
    gain = otf / (otf * otf + balance * laplacian_power(*padded.shape[-2:]))
    out = torch.fft.irfft2(torch.fft.rfft2(padded) * gain, s=padded.shape[-2:])
    return out[:, ph : ph + image.shape[-2], pw : pw + image.shape[-1]].float().clamp_(0, 1)


class PhysicsDeblur:
    """Wiener deconvolution with the short-exposure (tilt-removed) turbulence OTF at ``dr0`` (docs/physics.md §4).

    With depth modulation M (paper Eq. 4: blurred = M·(I ⊛ PSF) + (1 − M)·I), the effective OTF is
    M·T·H + (1 − M); ``modulation`` is the image's mean M (1: the whole path at ``dr0``).

    Args:
        dr0: D/r0 of the path; lambda_over_d_px: λ/(D·ifov), the diffraction angle in pixels (2 = Nyquist).
        balance: weight of the Laplacian smoothness prior (regularisation); default ``default_balance(dr0)``.
        modulation: mean depth modulation M in (0, 1].
    """

    def __init__(
        self,
        dr0: float,
        lambda_over_d_px: float = 2.0,
        balance: float | None = None,
        modulation: float = 1.0,
        alpha: float = 1.0,
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
        self.dr0, self.lambda_over_d_px, self.balance = float(dr0), float(lambda_over_d_px), float(balance)
        self.modulation, self.alpha = float(modulation), float(alpha)
        self._otf: dict[tuple[int, int], torch.Tensor] = {}

    def otf(self, height: int, width: int) -> torch.Tensor:
        """The effective OTF on the rfft2 grid of a (height, width) image after ``wiener_padding``."""
        if (height, width) not in self._otf:
            ph, pw = wiener_padding(height, width)
            h = image_otf(height + 2 * ph, width + 2 * pw, self.dr0, self.lambda_over_d_px, self.alpha)
            self._otf[(height, width)] = self.modulation * h + (1 - self.modulation)
        return self._otf[(height, width)]

    def __call__(self, image: torch.Tensor) -> torch.Tensor:
        return wiener_deconvolve(image, self.otf(*image.shape[-2:]), self.balance)


@dataclass
class _Frame:
    raw: np.ndarray  # (H,W,C) float32
    gray: np.ndarray  # (H,W) uint8
    flows: list = field(default_factory=list)  # per round: (H,W,2) backward flow onto that round's reference
    warped: list = field(default_factory=list)  # per round: the frame unwarped, (H,W,C) float32


class ClipRestorer:
    """Restore a clip of a static scene by registration, fusion and deblurring over a sliding window.

    Args:
        temporal: frames per window (≥ 2).
        passes: registration rounds (≥ 1); each refines the reference from the previous round's fusion.
        fusion: "mean" or "robust" (pixels weighted by their agreement with the reference).
        deblur: "none", a :class:`PhysicsDeblur`, or any callable (3,H,W) → (3,H,W) (e.g. a model's ``restore``).
        preset: registration accuracy, a key of ``d2turb.registration.DIS_PRESETS``.
        stabilise: remove a global shift per frame (camera shake) before the dense registration.
        fallback: use the single frame where its residual against the fusion stays high (moving objects).
    """

    def __init__(
        self,
        temporal: int = DEFAULT_TEMPORAL,
        passes: int = 2,
        fusion: str = "mean",
        deblur="none",
        preset: str = "medium",
        stabilise: bool = True,
        fallback: bool = True,
    ):
        if not isinstance(temporal, int) or isinstance(temporal, bool) or temporal < 2:
            raise D2TurbError(f"--temporal must be an integer >= 2, got {temporal!r}")
        if not isinstance(passes, int) or passes < 1:
            raise D2TurbError(f"passes must be an integer >= 1, got {passes!r}")
        if fusion not in FUSIONS:
            raise D2TurbError(f"unknown fusion {fusion!r}; choose one of {', '.join(FUSIONS)}")
        if not (deblur == "none" or callable(deblur)):
            raise D2TurbError(f"deblur must be 'none' or a callable, got {deblur!r}")
        self.temporal, self.passes, self.fusion = temporal, passes, fusion
        self.deblur = None if deblur == "none" else deblur
        self.stabilise, self.fallback = stabilise, fallback
        self.flow = DenseFlow(preset)

    # -- the stream ------------------------------------------------------------------------------------------------
    def restore(self, frames: Iterable) -> Iterator[ClipFrame]:
        """Restored frames in order, one per input frame ((3,H,W) tensors or (H,W,3) arrays in [0,1]), computed
        with a bounded lookahead. Raises ``D2TurbError`` for frames of different sizes or a clip of < 2 frames."""
        n, passes = self.temporal, self.passes
        buf: dict[int, _Frame] = {}
        length = None
        shape = None
        done = [0] * (passes + 1)  # done[k]: frames whose round k is computed (k = 0: read); next output = done[0]
        emitted = 0
        source = iter(frames)
        self._sums: dict[int, tuple] = {}  # level → (lo, hi, running sum, updates since recomputed)
        self.buffered = 0  # frames held in memory (bounded by the window, not by the clip's length)
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
                        shape = raw.shape
                    elif raw.shape != shape:
                        raise D2TurbError(
                            f"frame {done[0]} is {raw.shape[1]}x{raw.shape[0]}, the clip's first is "
                            f"{shape[1]}x{shape[0]}: all frames of a clip must have one size"
                        )
                    buf[done[0]] = _Frame(raw, to_gray_u8(raw))
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
            starts = [window_start(i, n, length) for i in [emitted, *done[1:]]]
            needed = min(starts + [c[0] for c in self._sums.values()])  # running sums subtract their old frames
            if length is None:  # the end may still shift the last windows back by up to n frames
                needed = min(needed, done[0] - n)
            for i in [i for i in buf if i < needed]:
                del buf[i]
            self.buffered = len(buf)
            if not progressed and length is not None:
                raise RuntimeError("clip restoration made no progress")  # pragma: no cover - a logic error

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
            return buf[j].raw if level == 0 else buf[j].warped[level - 1]

        if cached is None or cached[3] >= _RESUM or cached[0] > lo or cached[1] > hi or cached[1] <= lo:
            total = np.sum([image(j) for j in members], axis=0, dtype=np.float32)
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
        frame.flows.append(flow)
        frame.warped.append(remap(frame.raw, flow))

    def _output(self, buf: dict, index: int, length: int | None) -> ClipFrame:
        fused = self._reference(buf, index, self.passes, length)
        if self.fusion == "robust":
            fused = self._robust([buf[j].warped[-1] for j in self._window(buf, index, length)], fused)
        frame = buf[index]
        blend = np.zeros(fused.shape[:2], dtype=np.float32)
        if self.fallback:
            blend = self._fallback_share(frame.warped[-1], fused)
            if blend.any():
                fused = fused + blend[..., None] * (frame.raw - fused)
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


def restore_clip(frames: Iterable, **kwargs) -> Iterator[ClipFrame]:
    """``ClipRestorer(**kwargs).restore(frames)``: see :class:`ClipRestorer`."""
    return ClipRestorer(**kwargs).restore(frames)


__all__ = ["ClipRestorer", "ClipFrame", "PhysicsDeblur", "restore_clip", "window_start", "wiener_deconvolve"]
