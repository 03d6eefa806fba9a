"""Clip restoration: remove the tilt that a single frame cannot see by registering the frames of a sliding window to
a common reference, fusing them and deblurring the result (docs/clips.md).

For output frame t, the window W(t) holds the ``temporal`` frames around t (shifted inward at the clip's ends).
Each frame i is registered to a reference of its own window, in ``passes`` rounds:

0. camera motion (``clip.camera``, ``stabilise``): each frame's global shift against the mean of the frames placed
   before it (the median of a dense flow at ≤ 256 px) places it on a *canvas* (the first frame's view) where a shaking
   camera's frames line up;
1. reference R⁰_i = mean of the frames of W(i) placed on the canvas (geometrically the mean tilt, blurred);
   global shift of frame i against it (phase correlation);
2. round k: dense backward flow of frame i onto R^(k−1)_i (OpenCV DIS, started from the previous round),
   frame i unwarped; R^k_i = mean of the unwarped frames of W(i) (sharper, same geometry);
3. output t = fusion of the last round's unwarped frames of W(t) (mean; robust: each pixel weighted by its
   agreement with the reference; fba: Fourier burst accumulation, clip/fusion.py); where the frame's own
   residual stays high (a moving object) the single frame is used instead (no ghost); the fusion is moved from the
   canvas to W(t)'s mean camera pose (bicubic; near a jump, that of the frames around t) and where W(t)'s frames do
   not all see the scene (the borders a shake uncovers) frame t itself is used; then deblurred (none, a physics
   Wiener filter, or a model) and the deblur's over- and undershoots limited (``clip.deblur.tone_guard``).

Memory holds about 2·temporal·passes frames whatever the clip's length (a stream). Assumes a static scene seen by a
static or slowly moving camera; moving objects fall back to the single frame (not restored).
"""

from __future__ import annotations

import collections
import concurrent.futures
import functools
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from d2turb.clip.camera import CameraTrack
from d2turb.clip.deblur import tone_guard
from d2turb.clip.fusion import SharpestFusion, coarse_grey, fourier_burst_accumulation, sharp_coefficients
from d2turb.clip.registration import (
    DenseFlow,
    check_registrable,
    global_shift_px,
    remap,
    shift_flow,
    to_gray_u8,
    to_hwc,
    unit_float,
)
from d2turb.defaults import CLIP_FUSIONS, DEFAULT_FUSION, DEFAULT_TEMPORAL
from d2turb.errors import D2TurbError

FUSIONS = CLIP_FUSIONS
# the last round's unwarped frames (what the fusion averages) are held as 8 bits where the frame is (remapped from the
# 8-bit frame, rounded to nearest: ±0.5 grey levels per frame, about 0.07 after a mean of 16, far below the fusion's
# noise; a quarter of float32), else as float16 (relative error 2^-11)
STORE_DTYPE = np.float16
_RESUM = 256  # running window sums are recomputed from scratch after this many updates (float32 drift)
_FALLBACK_BOX = 15  # px: residuals are averaged over this box before the moving-object test
_FALLBACK_LOW, _FALLBACK_HIGH = 3.0, 6.0  # in units of the frame's robust residual scale: blend from → to
_CHANNEL_MEAN = {c: np.full((1, c), 1 / c, np.float32) for c in (2, 3, 4)}  # cv2.transform: the mean over channels


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


def window_start(index: int, temporal: int, length: int | None) -> int:
    """First frame of W(index): centred, shifted inward at the clip's ends (``length`` None: end not known yet)."""
    lo = max(0, index - temporal // 2)
    if length is not None:
        lo = min(lo, max(0, length - temporal))
    return lo


@dataclass
class _Frame:
    raw: np.ndarray  # (H,W,C) uint8 when that holds the float32 frame exactly (8-bit input), else float32; see .image
    gray: np.ndarray  # (H,W) uint8
    flows: list = field(default_factory=list)  # the last round's (H,W,2) backward flow onto its reference
    # per round: the frame unwarped; rounds before the last only feed the next round's reference, which DIS reads as
    # 8-bit grey, so they hold the frame's 8-bit luma unwarped, (H,W,1) uint8 (a twelfth of the memory and the remap);
    # the last round, which the fusion averages, the colour frame (H,W,C): uint8 for 8-bit frames, else STORE_DTYPE
    warped: list = field(default_factory=list)
    sharp: object = None  # fusion "sharpest": the last round's SharpCoefficients (as long as that round's image)
    coarse: object = None  # fusion "sharpest": coarse grey of the image the last round's reference averages
    canvas_gray: np.ndarray | None = None  # (H,W,1) uint8: the grey placed on the canvas (``stabilise``), else None

    def image(self) -> np.ndarray:
        """The frame as (H,W,C) float32 in [0,1] (bit-identical to the frame given: k/255 in float32)."""
        return _image_of(self.raw)


def _image_of(raw: np.ndarray) -> np.ndarray:
    """A held frame (uint8 or float) as (H,W,C) float32 in [0, 1] (see :meth:`_Frame.image`)."""
    return _as_float(raw) if raw.dtype == np.uint8 else raw


def _as_float(image: np.ndarray) -> np.ndarray:
    """A held image in [0, 1] as float32 (8-bit ones scaled by 1/255)."""
    return unit_float(image) if image.dtype == np.uint8 else image.astype(np.float32)


def _compact(raw: np.ndarray) -> np.ndarray:
    """``raw`` as uint8 when that is lossless (an 8-bit frame read as k/255: a quarter of the memory), else itself."""
    q = np.rint(raw * np.float32(255)).clip(0, 255).astype(np.uint8)
    return q if np.array_equal(q.astype(np.float32) / np.float32(255), raw) else raw


class ClipRestorer:
    """Restore a clip of a static scene by registration, fusion and deblurring over a sliding window.

    Args:
        temporal: frames per window (≥ 2).
        passes: registration rounds (≥ 1); each refines the reference from the previous round's fusion.
        fusion: "mean", "robust" (pixels weighted by their agreement with the reference), "fba" (Fourier burst
            accumulation: each frequency mostly from the frames that kept it best) or "sharpest" (per coefficient the
            frame that kept it best; ``clip/fusion.py``).
        deblur: "none", a :class:`PhysicsDeblur`, a :class:`BlindDeblur` (what ``restore --temporal`` uses), or any
            callable (3,H,W) → (3,H,W) (e.g. a model's ``restore``); one with an ``observe`` method is first given
            each :class:`ClipFrame` (its flow, before the deblur).
        preset: registration accuracy, a key of ``d2turb.clip.registration.DIS_PRESETS`` (default "fast": the flow at
            half resolution, as good as "medium" after fusion on the validation clips and 4× faster; docs/clips.md).
        stabilise: follow the camera (shake, jumps): frames are placed on one canvas by their global shift before the
            dense registration, and each output is moved back to its window's camera pose (``clip.camera``).
        fallback: use the single frame where its residual against the fusion stays high (moving objects).
        tone_guard: limit the deblur's over- and undershoots by the tones left (:func:`~d2turb.clip.deblur.tone_guard`:
            no crushed shadows or bright rims).

    Returns:
        :meth:`restore` yields one :class:`ClipFrame` per input frame, in order.

    Shape:
        frames: (3, H, W) float tensors or (H, W, 3) arrays in [0, 1], or (H, W, 3) uint8; all of one size.
        ClipFrame.restored, .fused: (3, H, W) float32 in [0, 1]; .bwd_flow_px: (2, H, W); .fallback: (H, W).
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
        tone_guard: bool = True,
    ):
        if not isinstance(temporal, int) or isinstance(temporal, bool) or temporal < 2:
            raise D2TurbError(f"temporal must be an integer >= 2, got {temporal!r}", param="temporal")
        if not isinstance(passes, int) or isinstance(passes, bool) or passes < 1:
            raise D2TurbError(f"passes must be an integer >= 1, got {passes!r}")
        if fusion not in FUSIONS:
            raise D2TurbError(f"unknown fusion {fusion!r}; choose one of {', '.join(FUSIONS)}")
        if not (deblur == "none" or callable(deblur)):
            raise D2TurbError(f"deblur must be 'none' or a callable, got {deblur!r}")
        self.temporal, self.passes, self.fusion = temporal, passes, fusion
        self.deblur = None if deblur == "none" else deblur
        self.stabilise, self.fallback, self.tone_guard = stabilise, fallback, tone_guard
        DenseFlow(preset)  # an unknown preset is an error now, not at the first frame
        self.preset = preset
        self.flow = None  # a fresh solver per clip
        self._pyramids = None  # the sharpest fusion's pyramids' thread while a clip streams

    # -- the stream ------------------------------------------------------------------------------------------------
    def restore(self, frames: Iterable) -> Iterator[ClipFrame]:
        """Restored frames in order, one per input frame ((3,H,W) tensors or (H,W,3) arrays in [0,1], or 8-bit frames
        as (H,W,3) uint8 arrays), computed
        with a bounded lookahead. Raises ``D2TurbError`` for frames of different sizes or a clip of < 2 frames.

        The deblur of frame t runs in a thread of its own while frame t + 1 is registered and fused (one frame in
        flight, in order): the two stages' single-threaded parts then share the cores (docs/clips.md, speed)."""
        fused = self._fused(frames)
        if self.deblur is None:
            yield from fused
            return
        observe = getattr(self.deblur, "observe", None)  # a deblur that reads more than the fused frame
        with concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="d2turb-deblur") as pool:
            pending: collections.deque = collections.deque()
            try:
                for frame in fused:
                    if observe is not None:
                        observe(frame)
                    pending.append((frame, pool.submit(self._deblur, frame.fused)))
                    if len(pending) > 1:
                        yield self._deblurred(*pending.popleft())
                while pending:
                    yield self._deblurred(*pending.popleft())
            finally:
                for _, job in pending:
                    job.cancel()

    def _deblur(self, fused: torch.Tensor) -> torch.Tensor:
        """The deblur of a fused frame, its over- and undershoots limited by the tones left (``tone_guard``)."""
        out = self.deblur(fused)
        return tone_guard(fused, out) if self.tone_guard and out is not fused else out

    @staticmethod
    def _deblurred(frame: ClipFrame, job) -> ClipFrame:
        frame.restored = job.result()
        return frame

    def _fused(self, frames: Iterable) -> Iterator[ClipFrame]:
        """The stream of :meth:`restore` before the deblur (``restored`` is ``fused``). The sharpest fusion of output t
        runs in a thread of its own while the next frames register (one output in flight, in order), as the deblur
        does: its array work then shares the two cores with the registration."""
        if self.fusion != "sharpest":
            yield from self._stream(frames)
            return
        with (
            concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="d2turb-fuse") as pool,
            concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="d2turb-pyramid") as pyramids,
        ):
            pending: collections.deque = collections.deque()
            try:
                for job in self._stream(frames, pool, pyramids):
                    pending.append(job)
                    if len(pending) > 1:
                        yield pending.popleft().result()
                while pending:
                    yield pending.popleft().result()
            finally:  # a stream closed early: drop what is queued (outputs and pyramids), finish what runs
                pool.shutdown(wait=True, cancel_futures=True)
                pyramids.shutdown(wait=True, cancel_futures=True)

    def _stream(self, frames: Iterable, pool=None, pyramids=None) -> Iterator:
        """Read, register and fuse: the outputs in order (with ``pool``, Futures of them; see :meth:`_output`; with
        ``pyramids``, the sharpest fusion's per-frame pyramids are computed there)."""
        self._pyramids = pyramids
        source = iter(frames)
        passes = self.passes
        buf: dict[int, _Frame] = {}
        length = None
        shape = None
        done = [0] * (passes + 1)  # done[k]: frames whose round k is computed (k = 0: read); next output = done[0]
        emitted = 0
        self.flow = None
        self._camera = CameraTrack(self.temporal) if self.stabilise else None
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
                    raw = to_hwc(item)  # float32 in [0, 1] (an 8-bit frame as k/255)
                    gray = to_gray_u8(raw)
                    stored = isinstance(item, np.ndarray) and item.dtype == np.uint8 and item.ndim == 3
                    raw = np.ascontiguousarray(item) if stored else _compact(raw)  # 8-bit frames held as uint8
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
                    buf[done[0]] = _Frame(raw, gray)
                    if self._camera is not None:
                        buf[done[0]].canvas_gray = self._camera.place(done[0], gray)
                    done[0] += 1
                progressed = True
            total = length if length is not None else done[0]
            for k in range(1, passes + 1):  # round k of frame i needs round k-1 of W(i)
                # no further ahead than the next round (or output) needs: once the clip's end is read, every window
                # is ready, and running ahead would hold a window more of unwarped frames and flows (1080p: 0.2 GB)
                need = self._window_end(done[k + 1] if k < passes else emitted, length)
                while done[k] < min(total, need) and self._window_ready(done[k], k - 1, done, length):
                    self._register(buf, done[k], k, length)
                    done[k] += 1
                    progressed = True
            while emitted < done[passes] and self._window_ready(emitted, passes, done, length):
                yield self._output(buf, emitted, length, pool)
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
        for j in [j for j in buf if j < max(*readers, emitted)]:
            frame = buf[j]
            if j < emitted:
                frame.flows = []  # read by its next round and its own output only (1080p: 16.6 MB a frame)
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

    def _window_end(self, index: int, length: int | None) -> int:
        """One past the last frame of W(index)."""
        lo = window_start(index, self.temporal, length)
        return lo + self.temporal if length is None else min(length, lo + self.temporal)

    def _window_ready(self, index: int, level: int, done: list, length: int | None) -> bool:
        return done[level] >= self._window_end(index, length)

    def _window(self, buf: dict, index: int, length: int | None) -> list[int]:
        return list(range(window_start(index, self.temporal, length), self._window_end(index, length)))

    def _reference(self, buf: dict, index: int, level: int, length: int | None) -> np.ndarray:
        """Mean of level ``level`` (0: raw frames, k: round k's unwarped frames) over W(index), from a running sum
        updated by the frames entering and leaving the window (recomputed every ``_RESUM`` updates)."""
        members = self._window(buf, index, length)
        lo, hi = members[0], members[-1] + 1
        cached = self._sums.get(level)

        def image(j):  # levels before the last only feed a round's reference, which DIS reads as 8-bit grey
            if level == 0:
                return buf[j].gray[..., None] if buf[j].canvas_gray is None else buf[j].canvas_gray
            return buf[j].warped[level - 1]

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
        return total / np.float32((hi - lo) * (255 if image(lo).dtype == np.uint8 else 1))

    def _register(self, buf: dict, index: int, k: int, length: int | None) -> None:
        frame = buf[index]
        ref = self._reference(buf, index, k - 1, length)
        ref_gray = to_gray_u8(ref)
        if k == 1:
            init = shift_flow(frame.gray.shape, *global_shift_px(ref_gray, frame.gray)) if self.stabilise else None
        else:
            init = frame.flows[-1]
        flow = self.flow(ref_gray, frame.gray, init)
        # held as float16 (1080p: 8.3 MB instead of 16.6 a frame, up to two windows of them; 0.004 px resolution below
        # 8 px): it starts the next round's search and becomes the output's bwd_flow_px (float32 again)
        frame.flows = [cv2.multiply(flow, 1.0, dtype=cv2.CV_16F)]  # as numpy's astype, in a third of its time
        if k == self.passes and self._camera is not None:  # the pose, to the dense flow's accuracy: its median
            step = max(1, int(math.sqrt(flow.shape[0] * flow.shape[1] / 65536)))  # about 65k pixels read
            self._camera.shifts[index] = tuple(float(v) for v in np.median(flow[::step, ::step].reshape(-1, 2), 0))
        if k < self.passes:  # uint8 in, uint8 out (cv2.remap rounds); the float32 flow is no longer needed
            frame.warped.append(remap(frame.gray[..., None], flow, consume=True))
            return
        if frame.raw.dtype == np.uint8:
            frame.warped.append(remap(frame.raw, flow, consume=True))
        else:
            frame.warped.append(remap(frame.raw, flow, consume=True).astype(STORE_DTYPE))
        if self.fusion == "sharpest":  # outliers against the median of the window's frames
            members = [buf[j] for j in self._window(buf, index, length)]
            for f in members:
                if f.coarse is None:
                    f.coarse = coarse_grey(f.image() if k == 1 else unit_float(f.warped[k - 2]))
            median = np.median(np.stack([f.coarse for f in members]), axis=0)
            # as held: uint8 or float16; with a pool, computed in its thread (a Future, which the fusion waits for)
            job = functools.partial(sharp_coefficients, frame.warped[-1], median)
            frame.sharp = job() if self._pyramids is None else self._pyramids.submit(job)

    def _output(self, buf: dict, index: int, length: int | None, pool=None):
        """Output ``index``: its ClipFrame, or with ``pool`` (the sharpest fusion) a Future of it: the fusion, which
        holds its own references to what it reads, then runs in that thread while the next frames register."""
        mean = None  # what the frame is compared with for moving objects (None: the fusion itself)
        if self.fusion in ("mean", "robust"):  # the others do not start from the window's mean
            fused = self._reference(buf, index, self.passes, length)
        if self.fusion == "robust":
            fused = self._robust([_as_float(buf[j].warped[-1]) for j in self._window(buf, index, length)], fused)
        elif self.fusion == "fba":
            fused = fourier_burst_accumulation([_as_float(buf[j].warped[-1]) for j in self._window(buf, index, length)])
        elif self.fusion == "sharpest":
            # the window's plain mean: the sharpest fusion's coefficients where no frame may be chosen, and what
            # moving objects are found against, as with the mean fusion (the sharpest fusion's own detail would
            # inflate the robust scale of the frame's residual and hide them: dost_street_clip, half a car ghosted)
            mean = self._reference(buf, index, self.passes, length)
            fused = functools.partial(
                self._fuse_sharpest, {j: buf[j].sharp for j in self._window(buf, index, length)}, mean
            )
        frame = buf[index]
        share = None  # the sharpest fusion's moving-object share, made beside it (it reads the mean, not the fusion)
        if self._pyramids is not None and self.fallback:
            share = self._pyramids.submit(self._fallback_share, frame.warped[-1], mean)
        pose = None
        if self._camera is not None:
            pose = self._camera.output_pose(index, self._window(buf, index, length), frame.gray.shape)
        job = functools.partial(
            self._finish, index, fused, mean, frame.warped[-1], frame.raw, frame.flows[-1], share, pose
        )
        return job() if pool is None else pool.submit(job)

    def _fuse_sharpest(self, window: dict, mean: np.ndarray) -> np.ndarray:
        """The sharpest fusion of ``window`` (index → SharpCoefficients, or a Future of them) with its mean frame."""
        return self._sharp.fuse(
            {j: c.result() if isinstance(c, concurrent.futures.Future) else c for j, c in window.items()}, mean
        )

    def _finish(self, index: int, fused, mean, warped, raw, flow, share=None, pose=None) -> ClipFrame:
        """The output frame from its fusion (an array, or a call that fuses), the moving-object fallback (``share``:
        a Future of it, or None to compute it here), the frame's own images and the output's camera pose (a
        :class:`~d2turb.clip.camera.OutputPose`, None without ``stabilise``)."""
        fused = fused if isinstance(fused, np.ndarray) else fused()
        blend = np.zeros(fused.shape[:2], dtype=np.float32)
        if self.fallback:
            blend = self._fallback_share(warped, fused if mean is None else mean) if share is None else share.result()
        if pose is not None:
            fused, blend, flow = pose.apply(fused, blend, flow)
            if blend.any():  # the frame's own pixels moved by what its pose differs from the output's (sub-pixel)
                raw = pose.frame_at_output(raw)
            rows = np.flatnonzero(blend.any(axis=1))
            if rows.size:  # fused + blend·(image − fused) on the rows the fallback touches (fused is this output's own)
                part = slice(rows[0], rows[-1] + 1)
                step = np.subtract(_image_of(raw[part]), fused[part])
                step *= blend[part, :, None]
                fused[part] += step
        # (3,H,W) as a view of the (H,W,3) array (the writers want H,W,3 again); a deblur gets a contiguous copy made by
        # numpy (torch's allocator aligns large blocks to 2 MiB: malloc's heaps fragment, +0.2 GB peak at 1080p)
        fused = np.clip(fused, 0, 1, out=fused)
        fused_t = torch.from_numpy(fused if self.deblur is None else np.ascontiguousarray(fused.transpose(2, 0, 1)))
        if self.deblur is None:
            fused_t = fused_t.permute(2, 0, 1)
        camera = None if pose is None else tuple(float(v) for v in pose.frame_shift)
        return ClipFrame(index, fused_t, fused_t, flow, torch.from_numpy(blend), camera_px=camera)

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
        """Share of the single frame per pixel: 0 where the registered frame ``warped`` (as held: uint8, or float)
        agrees with the fusion within a few robust scales of its residual (box-averaged), rising to 1 where it stays
        far above (a moving object).
        On frames of ≥ 1 MP the box average is taken at half resolution (the box and the dilation span 15 px:
        the decision is smooth at that scale) and the robust scale from every 4th residual."""
        diff = cv2.absdiff(_as_float(warped), fused)  # OpenCV: a quarter of numpy's time at 1080p
        r = diff[..., 0] if diff.ndim == 2 or diff.shape[2] == 1 else cv2.transform(diff, _CHANNEL_MEAN[diff.shape[2]])
        r = r.reshape(diff.shape[:2])
        h, w = r.shape
        half = h * w >= 1 << 20
        box = _FALLBACK_BOX // 2 + 1 if half else _FALLBACK_BOX
        if half:
            r = cv2.resize(r, ((w + 1) // 2, (h + 1) // 2), interpolation=cv2.INTER_AREA)
        r = cv2.blur(r, (box, box))
        scale = max(1.4826 * float(np.median(r[::2, ::2] if half else r)), 1e-3)
        z = (r / scale - _FALLBACK_LOW) / (_FALLBACK_HIGH - _FALLBACK_LOW)
        share = np.clip(z, 0, 1).astype(np.float32)
        if not share.any():
            return np.zeros((h, w), np.float32) if half else share
        # grown by a disc (a square box printed square patches on real clips), then its edge softened by a box
        # average as wide as the growth: the share stays 1 over the object itself and fades over box/2 around it
        share = cv2.blur(cv2.dilate(share, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (box, box))), (box, box))
        return cv2.resize(share, (w, h), interpolation=cv2.INTER_LINEAR) if half else share


def restore_clip(frames: Iterable, **kwargs) -> Iterator[ClipFrame]:
    """``ClipRestorer(**kwargs).restore(frames)``: see :class:`ClipRestorer`."""
    return ClipRestorer(**kwargs).restore(frames)


__all__ = [
    "ClipRestorer",
    "ClipFrame",
    "restore_clip",
    "window_start",
]
