"""Live clip restoration (``restore --temporal N --preset fast``): the clip room cut to what a live camera's frame rate
allows on two cores (1280×720 at about 5× the default's speed; benchmarks/bench_clip_live.py; docs/clips.md, "The
live preset"). One pass over the stream, each frame touched once:

1. **register** (:class:`LiveRestorer`): frame i's 8-bit luma at ``scale`` (area-averaged; half size) is
   registered by DIS (OpenCV's ultrafast preset, mean normalisation) to the mean luma of W(i), the window centred on
   it (which sets the output's geometry: the mean tilt around the frame), then, started from that flow, by a finer
   DIS (``live_state.LIVE_DIS``) to the mean of the first round's registrations of the N frames up to i; the flow is
   upsampled to full size (bilinear, ×1/``scale``) and the frame remapped once: the tilt is smooth over the
   isoplanatic patch, so its flow at half size, upsampled, is what the fusion needs;
2. **fuse**: output t is the mean of the registered frames of its window W(t) (``window_start``, as the default's:
   centred, shifted inward at the clip's ends), kept as a running sum (the newest frame added, the oldest taken off;
   exact integers for 8-bit frames);
3. **deblur** (:func:`live_deblurred`): the blind deblur's (or a physics) Wiener filter on the luma alone, with the
   live registration's residual misregistration in its OTF, the tone guard on the luma, the change added to each
   channel.

No camera following, no global shift, no moving-object fallback (moving objects ghost), a single registration
resolution. Output t comes once input t + 2·(N − N//2 − 1) is read (30 frames at N = 32: a second at 30 frames/s;
issue 52 allows half a window plus a second), the first once input 2N − N//2 − 2 is. Memory holds about 2·N full-size
frames.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterable, Iterator

import cv2
import numpy as np
import torch

from d2turb.clip.blind import BlindDeblur
from d2turb.clip.deblur import PhysicsDeblur, check_deblur, tone_guard
from d2turb.clip.frames import ClipFrame
from d2turb.clip.live_state import LIVE_ROUNDS, LIVE_SCALE, LiveState, upsampled_flow
from d2turb.clip.registration import LUMA_BT601
from d2turb.clip.schedule import in_order, run_in, worker
from d2turb.defaults import DEFAULT_TEMPORAL
from d2turb.errors import D2TurbError

# the presets of ``restore --temporal`` and ``evaluate --clips`` (``--preset``): the live restorer, or the clip room
# with a DIS preset of ``registration.DIS_PRESETS``. The default's DIS preset is called "fast" in the library (its
# name since 2026-11); on the command line it is "balanced" and "fast" is the live preset (issue 52 names it so)
LIVE_PRESET = "fast"
DEFAULT_PRESET = "balanced"
PRESETS = {"fast": None, "balanced": "fast", "medium": "medium", "fine": "fine"}  # command line → DIS preset
# what the live preset gives up on the blind test set: its largest loss per bin against the default (its first 30
# clips, --temporal 32, the blind deblur; against 0e53848's default, offset removed: +0.44 / -0.06 / -0.21 dB weak /
# medium / strong; plain PSNR +0.15 / +0.04 / -0.03; docs/clips.md "The live preset"), said in the help of --preset
# (commands/restore.py; tests/test_clip_live.py checks it)
LIVE_LOSS_DB = 0.21
LIVE_LOSS_PLAIN_DB = 0.03
LIVE_X264_PRESET = "ultrafast"  # the live preset's mp4 (restore.clip_out): 720p at 12 against 29 ms a frame
_PREFETCH = 4  # decoded frames waiting for the registration (a reader thread of their own)


def dis_preset(preset: str) -> str | None:
    """The DIS preset (``registration.DIS_PRESETS``) of a command line ``--preset``; None for the live one."""
    if preset not in PRESETS:
        raise D2TurbError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}", param="preset")
    return PRESETS[preset]


class LiveRestorer:
    """Restore a stream in one pass at a live camera's frame rate (the module's docstring says how).

    Args:
        temporal: frames per window (≥ 2).
        deblur: "none", a :class:`~d2turb.clip.blind.BlindDeblur` (``restore --preset fast``'s), a
            :class:`~d2turb.clip.deblur.PhysicsDeblur`, or any callable (3,H,W) → (3,H,W) (run as the default runs it:
            :func:`~d2turb.clip.pipeline.deblurred`).
        scale: the registration's size relative to the frame (0 < scale ≤ 1).
        rounds: DIS calls a frame (1 or 2).
        tone_guard: limit the deblur's over- and undershoots by the tones left (on the luma).
        threaded: read the frames in a thread of their own and deblur in another; False: all in the caller's
            thread (the same outputs to the bit).

    Returns:
        :meth:`restore` yields one :class:`~d2turb.clip.ClipFrame` per input frame, in order (``fallback`` all 0,
        ``camera_px`` None).

    Shape:
        frames: (3, H, W) float tensors or (H, W, C) arrays in [0, 1], or (H, W, C) uint8; all of one size.
    """

    def __init__(
        self,
        temporal: int = DEFAULT_TEMPORAL,
        deblur="none",
        scale: float = LIVE_SCALE,
        rounds: int = LIVE_ROUNDS,
        tone_guard: bool = True,
        threaded: bool = True,
    ):
        if not isinstance(temporal, int) or isinstance(temporal, bool) or temporal < 2:
            raise D2TurbError(f"temporal must be an integer >= 2, got {temporal!r}", param="temporal")
        if not 0 < scale <= 1:
            raise D2TurbError(f"the live registration's scale must be in (0, 1], got {scale!r}")
        if rounds not in (1, 2):
            raise D2TurbError(f"the live registration runs 1 or 2 rounds, got {rounds!r}")
        if not (deblur == "none" or callable(deblur)):
            raise D2TurbError(f"deblur must be 'none' or a callable (3,H,W) -> (3,H,W), got {deblur!r}")
        self.temporal, self.scale, self.rounds = temporal, float(scale), rounds
        self.deblur = None if deblur == "none" else deblur
        self.tone_guard, self.threaded = tone_guard, threaded

    def restore(self, frames: Iterable) -> Iterator[ClipFrame]:
        """Restored frames in order, one per input frame, each as soon as its window is registered."""
        with (
            worker("d2turb-live-deblur", self.threaded and self.deblur is not None) as deblur_pool,
            _Reader(frames, self.threaded) as source,
        ):
            fused = LiveState(self).outputs(source)
            if self.deblur is None:
                yield from fused
            else:
                yield from in_order(self._deblur_jobs(fused, run_in(deblur_pool)))

    def _deblur_jobs(self, fused: Iterator[ClipFrame], submit) -> Iterator:
        observe = getattr(self.deblur, "observe", None)
        for frame in fused:
            if observe is not None:
                observe(frame)
            yield submit(lambda frame=frame: self._deblurred(frame))

    def _deblurred(self, frame: ClipFrame) -> ClipFrame:
        frame.restored = live_deblurred(self.deblur, frame.fused, self.tone_guard)
        return frame


class _Reader:
    """The frames of an iterable, read ``_PREFETCH`` ahead in a thread of their own (decoding beside the
    registration), or in the caller's thread; the reader's exceptions are raised where the frame is taken."""

    _END = object()

    def __init__(self, frames: Iterable, threaded: bool):
        self.frames, self.threaded = frames, threaded
        self._stop = threading.Event()

    def __enter__(self):
        if not self.threaded:
            return iter(self.frames)
        self._queue: queue.Queue = queue.Queue(_PREFETCH)
        self._thread = threading.Thread(target=self._read, name="d2turb-live-read", daemon=True)
        self._thread.start()
        return self._items()

    def _read(self) -> None:
        try:
            for item in self.frames:
                if not self._put(item):
                    return
            self._put(self._END)
        except BaseException as exc:  # handed to the consumer
            self._put(exc)

    def _put(self, item) -> bool:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _items(self) -> Iterator:
        while True:
            item = self._queue.get()
            if item is self._END:
                return
            if isinstance(item, BaseException):
                raise item
            yield item

    def __exit__(self, *exc):
        if self.threaded:
            self._stop.set()
            self._thread.join()
        return False


# the residual misregistration of the live registration, σ per axis (px), put into the Wiener filter's OTF as a
# Gaussian (PhysicsDeblur's jitter_px): its coarser flow leaves each frame further off than the default's, so the mean
# is blurred more; 0.4 px brought the blind test set's first 6 clips from -0.25 to +0.06 dB against the default
# (docs/clips.md, "The live preset")
LIVE_JITTER_PX = 0.4


def _with_live_jitter(deblur: PhysicsDeblur) -> PhysicsDeblur:
    """``deblur`` with the live registration's residual jitter in its OTF (``LIVE_JITTER_PX`` added to its own in
    quadrature), made once per deblur."""
    twin = getattr(deblur, "_live_twin", None)
    if twin is None:
        if LIVE_JITTER_PX <= 0:
            twin = deblur
        else:
            jitter = float(np.hypot(deblur.jitter_px, LIVE_JITTER_PX))
            twin = PhysicsDeblur(deblur.dr0, deblur.lambda_over_d_px, deblur.balance, deblur.modulation, deblur.alpha,
                                 jitter, deblur.boost_only, deblur.prior)  # fmt: skip
        deblur._live_twin = twin
    return twin


def live_deblurred(deblur, fused: torch.Tensor, guard: bool = True) -> torch.Tensor:
    """The live preset's deblur of one fused frame (``LiveRestorer`` and ``evaluate --clips --preset fast`` both run
    it): a :class:`PhysicsDeblur` (a :class:`~d2turb.clip.blind.BlindDeblur`'s after its decision on this, its first,
    frame) filters the luma Y alone and the tone guard limits Y's over- and undershoots; the change is added to each
    channel, ``fused + (guard(G∗Y) − Y)``, in [0, 1] (a third of the FFTs and of the guard). Another deblur runs as the
    default runs it (each channel, the tone guard on each). Returns ``fused`` itself where nothing is deblurred.

    Shape:
        fused: (C, H, W) float32 in [0, 1]; output: the same.
    """
    decide = getattr(deblur, "decide", None)
    if decide is not None and getattr(deblur, "record", None) is None:
        if isinstance(deblur, BlindDeblur):  # the live frames are resampled bilinearly: read as they are
            deblur.decide(fused, resampled="bilinear")
        else:
            decide(fused)
    inner = deblur.deblur if decide is not None else deblur
    if inner is None:
        return fused
    if isinstance(inner, PhysicsDeblur):
        inner = _with_live_jitter(inner)
    if not isinstance(inner, PhysicsDeblur) or fused.shape[0] != 3:
        out = check_deblur(inner, fused)
        return tone_guard(fused, out) if guard and out is not fused else out
    image = np.ascontiguousarray(fused.permute(1, 2, 0).numpy(), dtype=np.float32)  # (H,W,3): a view when it is one
    luma = cv2.transform(image, LUMA_BT601[None]).reshape(image.shape[:2])
    y = torch.from_numpy(luma)[None]
    filtered = inner(y)
    if guard:
        filtered = tone_guard(y, filtered)
    change = filtered[0].numpy()
    change -= luma
    out = image + change[..., None]
    np.clip(out, 0, 1, out=out)
    return torch.from_numpy(out).permute(2, 0, 1)


__all__ = [
    "DEFAULT_PRESET",
    "LIVE_PRESET",
    "LIVE_ROUNDS",
    "LIVE_SCALE",
    "LIVE_X264_PRESET",
    "PRESETS",
    "LiveRestorer",
    "dis_preset",
    "live_deblurred",
    "upsampled_flow",
]
