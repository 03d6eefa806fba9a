"""Clip restoration: remove the tilt that a single frame cannot see by registering the frames of a sliding window to
a common reference, fusing them and deblurring the result (docs/clips.md).

For output frame t, the window W(t) holds the ``temporal`` frames around t (shifted inward at the clip's ends); with
``lookahead`` L (a stream's), the windows of the rounds and of the output reach at most L frames past t together.
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
   residual stays high, or the window's frames disagree more than registration explains (a moving object and its
   trail), the single frame is used instead (no ghost), unwarped by the flow around it; the fusion is moved from the
   canvas to W(t)'s mean camera pose (bicubic; near a jump, that of the frames around t) and where W(t)'s frames do
   not all see the scene (the borders a shake uncovers) frame t itself is used; then deblurred (none, a physics
   Wiener filter, or a model) and the deblur's over- and undershoots limited (``clip.deblur.tone_guard``).

Memory holds about 2·temporal·passes frames whatever the clip's length (a stream). Assumes a static scene seen by a
static or slowly moving camera; moving objects fall back to the single frame (not restored).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator

import numpy as np
import torch

from d2turb.clip.deblur import ClipDeblur, check_deblur, deblur_in_linear_light, tone_guard
from d2turb.clip.frames import ClipFrame, window_start
from d2turb.clip.fusion import FUSION_REGISTRY, fusion_class, make_fusion
from d2turb.clip.registration import DenseFlow
from d2turb.clip.schedule import in_order, outputs, run_in, worker
from d2turb.clip.state import ClipState
from d2turb.defaults import DEFAULT_FUSION, DEFAULT_TEMPORAL
from d2turb.errors import D2TurbError

FUSIONS = tuple(FUSION_REGISTRY)  # the fusions built in (``defaults.CLIP_FUSIONS``, the command line's)


class ClipRestorer:
    """Restore a clip of a static scene by registration, fusion and deblurring over a sliding window.

    Args:
        temporal: frames per window (≥ 2).
        passes: registration rounds (≥ 1); each refines the reference from the previous round's fusion.
        fusion: a name in the fusion registry (:mod:`d2turb.clip.fusion`): "mean", "robust" (pixels weighted by their
            agreement with the reference), "fba" (Fourier burst accumulation: each frequency mostly from the frames
            that kept it best) or "sharpest" (per coefficient the frame that kept it best).
        deblur: "none", or a :class:`~d2turb.clip.deblur.ClipDeblur`: a :class:`PhysicsDeblur`, a
            :class:`BlindDeblur` (what ``restore --temporal`` uses), or any callable (3,H,W) → (3,H,W) (e.g. a model's
            ``restore``); one with an ``observe`` method is first given each :class:`ClipFrame` (its flow, before the
            deblur).
        preset: registration accuracy, a key of ``d2turb.clip.registration.DIS_PRESETS`` (default "fast": the flow at
            half resolution, as good as "medium" after fusion on the validation clips and 4× faster; docs/clips.md).
        stabilise: follow the camera (shake, jumps): frames are placed on one canvas by their global shift before the
            dense registration, and each output is moved back to its window's camera pose (``clip.camera``).
        fallback: use the single frame where its residual against the fusion stays high (moving objects).
        tone_guard: limit the deblur's over- and undershoots by the tones left (:func:`~d2turb.clip.deblur.tone_guard`:
            no crushed shadows or bright rims).
        threaded: overlap the stages in threads of their own (:meth:`restore`); False runs everything in the caller's
            thread, with the same outputs to the bit.
        linear_light: frames are sRGB-encoded values of light that air and optics blurred before the tone curve (a
            camera's footage): a physical deblur runs in linear light (:func:`deblurred`). Not the default: it gains
            +0.45 dB on field-realistic clips but loses up to 1 dB on clips blurred after encoding (our simulator's
            test clips; docs/clips_linear_light.md).
        lookahead: None (default): centred windows, output t waits for input t + 3·(temporal/2 − 1) with 2 rounds
            (the best windows for a file). An integer L >= 0: output t waits for input t + L at most: the windows of
            the rounds and of the output reach L frames ahead together (``clip.frames.lookahead_split``), the rest
            behind: a stream's latency (``restore -`` uses temporal/2 − 1; its quality cost: docs/clips.md, streams).

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
        threaded: bool = True,
        linear_light: bool = False,
        lookahead: int | None = None,
    ):
        self.check_settings(temporal, passes, fusion, preset, lookahead)
        if not (deblur == "none" or isinstance(deblur, ClipDeblur)):
            raise D2TurbError(f"deblur must be 'none' or a callable (3,H,W) -> (3,H,W), got {deblur!r}")
        self.temporal, self.passes, self.fusion = temporal, passes, fusion
        self.deblur = None if deblur == "none" else deblur
        self.stabilise, self.fallback, self.tone_guard = stabilise, fallback, tone_guard
        self.preset = preset
        self.threaded, self.linear_light, self.lookahead = threaded, linear_light, lookahead
        self.state: ClipState | None = None  # the state of the clip being (or last) restored

    @staticmethod
    def check_settings(temporal: int, passes: int, fusion: str, preset: str, lookahead: int | None = None) -> None:
        """D2TurbError, in one line, for settings a restorer refuses (before anything reads a clip)."""
        if not isinstance(temporal, int) or isinstance(temporal, bool) or temporal < 2:
            raise D2TurbError(f"temporal must be an integer >= 2, got {temporal!r}", param="temporal")
        if not isinstance(passes, int) or isinstance(passes, bool) or passes < 1:
            raise D2TurbError(f"passes must be an integer >= 1, got {passes!r}")
        if lookahead is not None and (not isinstance(lookahead, int) or isinstance(lookahead, bool) or lookahead < 0):
            raise D2TurbError(f"lookahead must be an integer >= 0, got {lookahead!r}", param="lookahead")
        fusion_class(fusion)  # an unknown fusion: one line naming the registered ones
        DenseFlow(preset)  # an unknown preset is an error now, not at the first frame

    def restore(self, frames: Iterable) -> Iterator[ClipFrame]:
        """Restored frames in order, one per input frame ((3,H,W) tensors or (H,W,3) arrays in [0,1], or 8-bit frames
        as (H,W,3) uint8 arrays), computed with a bounded lookahead. Raises ``D2TurbError`` for frames of different
        sizes or a clip of < 2 frames.

        Threads (``threaded``): the deblur of frame t runs in a thread of its own while frame t + 1 is registered and
        fused, and a threaded fusion (the sharpest) fuses output t in another while the next frames register, its
        per-frame preparation in a third (one output in flight at each, in order): the stages' single-threaded parts
        then share the cores (docs/clips.md, speed). The run's state is :attr:`state` (a fresh
        :class:`~d2turb.clip.state.ClipState` per call)."""
        fusion = make_fusion(self.fusion)
        state = ClipState(self.temporal, self.passes, fusion, self.preset, self.stabilise, self.lookahead)
        self.state = state
        threaded_fusion = self.threaded and fusion.threaded
        with (
            worker("d2turb-fuse", threaded_fusion) as fuse_pool,
            worker("d2turb-pyramid", threaded_fusion) as prepare_pool,
            worker("d2turb-deblur", self.threaded and self.deblur is not None) as deblur_pool,
        ):
            fused = in_order(outputs(state, frames, self.fallback, fuse_pool, prepare_pool))
            if self.deblur is None:
                yield from fused
            else:
                yield from in_order(self._deblur_jobs(fused, run_in(deblur_pool)))

    def _deblur_jobs(self, fused: Iterator[ClipFrame], submit) -> Iterator:
        observe = getattr(self.deblur, "observe", None)  # a deblur that reads more than the fused frame
        for frame in fused:
            if observe is not None:
                observe(frame)
            # the deblur gets a contiguous (3,H,W) copy made by numpy (torch's allocator aligns large blocks to 2 MiB:
            # malloc's heaps fragment, +0.2 GB peak at 1080p)
            frame.fused = torch.from_numpy(np.ascontiguousarray(frame.fused.numpy()))
            yield submit(lambda frame=frame: self._deblurred(frame))

    def _deblurred(self, frame: ClipFrame) -> ClipFrame:
        frame.restored = deblurred(self.deblur, frame, self.tone_guard, self.linear_light)
        return frame


def deblurred(deblur: ClipDeblur, frame: ClipFrame, guard: bool = True, linear_light: bool = False) -> torch.Tensor:
    """The deblur stage of the clip room, for one fused frame (``ClipRestorer`` and ``evaluate --clips`` both run it):
    ``deblur(frame.fused)`` checked at the boundary (with ``linear_light``, a physical deblur on the frame decoded to
    linear light: :func:`~d2turb.clip.deblur.deblur_in_linear_light`), its over- and undershoots limited by the tones
    left (``tone_guard``, with ``guard``), and not applied where the frame itself stands in for the fusion
    (``frame.fallback``: moving objects, uncovered borders): a single frame's codec blocks and noise are what a deblur
    sharpens (dost_street_clip's crossing car left blotches and block outlines on the road). A deblur's ``observe``
    is the caller's to call first.

    Shape:
        frame.fused: (C, H, W); frame.fallback: (H, W); output: (C, H, W) float32.
    """
    if linear_light and getattr(deblur, "linear_light", False):  # a physical deblur: where light is blurred
        out = deblur_in_linear_light(deblur, frame.fused, guard)
    else:
        out = check_deblur(deblur, frame.fused)
        if guard and out is not frame.fused:
            out = tone_guard(frame.fused, out)
    if out is not frame.fused and bool(frame.fallback.any()):
        out = torch.lerp(out, frame.fused, frame.fallback)  # out + share·(fused − out), in one pass
    return out


def restore_clip(frames: Iterable, **kwargs) -> Iterator[ClipFrame]:
    """``ClipRestorer(**kwargs).restore(frames)``: see :class:`ClipRestorer`."""
    return ClipRestorer(**kwargs).restore(frames)


__all__ = [
    "ClipRestorer",
    "deblurred",
    "ClipFrame",
    "FUSIONS",
    "restore_clip",
    "window_start",
]
