"""One clip's state while it is restored (:class:`ClipState`): the frames held, how far each stage has come, the
windows' running sums, the camera track, the dense-flow solver and the fusion. Made afresh by every
:meth:`ClipRestorer.restore <d2turb.clip.pipeline.ClipRestorer.restore>` (a restorer can restore clip after clip)."""

from __future__ import annotations

import math

import cv2
import numpy as np

from d2turb.clip.camera import CameraTrack
from d2turb.clip.frames import HeldFrame, as_float, channel_mean, lookahead_split, window_span, window_start
from d2turb.clip.fusion import Fusion
from d2turb.clip.registration import DenseFlow, check_registrable, is_large_frame
from d2turb.errors import D2TurbError

_RESUM = 256  # running window sums are recomputed from scratch after this many updates (float32 drift)
# registration rounds before the last, on frames of >= 1 MP, stop DIS's search this many pyramid levels above the
# preset's finest (they only start the last round's search and make its reference). 1080p "fast": 44 against 125 ms a
# call (one thread); simulated 1080p clips (an upscaled sunhays_outdoor scene at D/r0 2, 3, 4, 24 frames, offset
# removed, benchmarks/RESULTS.md 2026-12-08): restored -0.04 to +0.10 dB, fused -0.00 to +0.03 dB
EARLY_ROUND_COARSER = 1
# ... and the last round's patches a px further apart there ("fast": 5 against 4 px; 1080p: 89 against 117-131 ms a
# call, one thread; the simulated 1080p clips at 28751cb: restored -0.00 to +0.02 dB, fused -0.00 to -0.01 dB)
LAST_ROUND_STRIDE = {"fast": 5}
# an output's moving-object pixels also read the raw frames and last flows of this many frames before it
# (stages.object_average): they are held that much longer
OBJECT_REACH = 4


class ClipState:
    """The state of one clip's restoration.

    ``done[k]``: the frames whose level k is computed (0: read, k ≥ 1: registration round k); ``emitted``: the
    outputs made (the next output is frame ``emitted``); ``length``: the clip's length once its end is read;
    ``buffered``: frame images held (bounded by the window, not by the clip's length); ``ahead[level]``: how far
    past frame i the window over that level reaches (None: centred; :func:`~d2turb.clip.frames.lookahead_split`)."""

    def __init__(
        self, temporal: int, passes: int, fusion: Fusion, preset: str, stabilise: bool, lookahead: int | None = None
    ):
        self.temporal, self.passes, self.fusion, self.preset = temporal, passes, fusion, preset
        self.ahead = lookahead_split(lookahead, temporal, passes)
        self.frames: dict[int, HeldFrame] = {}
        self.done = [0] * (passes + 1)
        self.emitted = 0
        self.length: int | None = None
        self.shape: tuple | None = None
        self.flow_solver: DenseFlow | None = None  # the dense-flow solver, made at the first frame
        self.early_solver: DenseFlow | None = None  # ... of the rounds before the last (see flow_solver_for)
        self.camera = CameraTrack(temporal) if stabilise else None
        self.sums: dict = {}  # level (or "grey", "grey²": spread) → (lo, hi, running sum, updates since recomputed)
        self.buffered = 0

    # -- reading -------------------------------------------------------------------------------------------------
    def hold(self, item) -> None:
        """Read the next input frame (placed on the camera's canvas when the camera is followed)."""
        index = self.done[0]
        frame = HeldFrame.of(item)
        if self.shape is None:
            check_registrable(*frame.raw.shape[:2])
            self.shape = frame.raw.shape
        elif frame.raw.shape != self.shape:
            h, w = frame.raw.shape[:2]
            raise D2TurbError(
                f"frame {index} is {w}x{h}, the clip's first is {self.shape[1]}x{self.shape[0]}: all frames of a clip "
                "must have one size"
            )
        if self.flow_solver is None:
            h, w = frame.raw.shape[:2]
            large = is_large_frame(h, w)
            stride = LAST_ROUND_STRIDE.get(self.preset) if large else None
            self.flow_solver = DenseFlow(self.preset, patch_stride=stride)
            self.early_solver = DenseFlow(self.preset, EARLY_ROUND_COARSER) if large else self.flow_solver
        self.frames[index] = frame
        if self.camera is not None:
            frame.canvas_gray = self.camera.place(index, frame.gray)
        self.done[0] += 1

    def end(self) -> None:
        """The clip's end is read."""
        self.length = self.done[0]
        if self.length < 2:
            raise D2TurbError(f"a clip needs at least 2 frames, got {self.length}")

    def flow_solver_for(self, k: int) -> DenseFlow:
        """The dense-flow solver of registration round ``k``: the last round's at the preset's resolution; on frames of
        >= 1 MP the rounds before it ``EARLY_ROUND_COARSER`` levels coarser (they start the last round's search) and
        the last one's patches ``LAST_ROUND_STRIDE`` px apart."""
        return self.flow_solver if k >= self.passes else self.early_solver

    # -- windows -------------------------------------------------------------------------------------------------
    def window_start(self, index: int, level: int) -> int:
        """The first frame of W(index) over level ``level`` (what round level + 1, or the output, averages)."""
        return window_start(index, self.temporal, self.length, self.ahead[level])

    def window_end(self, index: int, level: int) -> int:
        """One past the last frame of W(index) over level ``level``."""
        return window_span(index, self.temporal, self.length, self.ahead[level])[1]

    def window_ready(self, index: int, level: int) -> bool:
        """Level ``level`` of every frame of W(index) is computed."""
        return self.done[level] >= self.window_end(index, level)

    def window(self, index: int, level: int) -> list[int]:
        """The frames of W(index) over level ``level``."""
        return list(range(*window_span(index, self.temporal, self.length, self.ahead[level])))

    def reference(self, index: int, level: int) -> np.ndarray:
        """Mean of level ``level`` (0: the frames' luma, k: round k's unwarped frames) over W(index), from a running sum
        updated by the frames entering and leaving the window (recomputed every ``_RESUM`` updates)."""
        lo, hi, total = self._window_sum(index, level, level, lambda j: self.frames[j].level_image(level))
        return total / np.float32((hi - lo) * (255 if self.frames[lo].level_image(level).dtype == np.uint8 else 1))

    def spread(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """(variance, mean) of the last round's unwarped frames' grey (the mean of their channels, unit range) over
        W(index), per pixel, float32, from running sums of the grey and its square; at half size (area-averaged) for
        frames of ≥ 1 MP (what reads it, ``stages.spread_share``, decides at that scale). The variance is high where
        the window's frames disagree after registration: a moving object, and the trail it leaves in the mean."""
        last = self.passes

        def grey(j):
            frame = self.frames[j]
            if frame.spread_grey is None:
                image = as_float(frame.warped[last - 1])
                h, w = image.shape[:2]
                if is_large_frame(h, w):
                    image = cv2.resize(image, ((w + 1) // 2, (h + 1) // 2), interpolation=cv2.INTER_AREA)
                    image = image.reshape(image.shape[:2] + (-1,))
                frame.spread_grey = channel_mean(image)
            return frame.spread_grey

        lo, hi, s1 = self._window_sum(index, last, "grey", grey)
        _, _, s2 = self._window_sum(index, last, "grey²", lambda j: np.square(grey(j)))
        n = np.float32(hi - lo)
        mean = s1 / n
        return np.maximum(s2 / n - mean * mean, 0), mean

    def _window_sum(self, index: int, level: int, key, image) -> tuple[int, int, np.ndarray]:
        """(lo, hi, Σ image(j) over W(index) = [lo, hi) over ``level``), float32, kept as ``sums[key]`` and updated by
        the frames entering and leaving the window (recomputed every ``_RESUM`` updates)."""
        members = self.window(index, level)
        lo, hi = members[0], members[-1] + 1
        cached = self.sums.get(key)
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
        self.sums[key] = (lo, hi, total, count)
        return lo, hi, total

    # -- memory --------------------------------------------------------------------------------------------------
    def release(self) -> None:
        """Free each frame's images once nothing left to compute reads them: level L's image (0: the raw frame, k:
        round k's unwarped frame) of frame j is read by the references of round L + 1 (windows from
        W(done[L+1]) on) and by the running sum of level L; the raw frame also by its own registration rounds and
        by the output's fallback; the last round by the outputs' fusion. Frames with nothing left are dropped."""
        n, passes, done, emitted = self.temporal, self.passes, self.done, self.emitted
        guard = done[0] - n if self.length is None else math.inf  # the end may still shift the last windows back
        readers = []
        for level in range(passes + 1):
            first = self.window_start(emitted if level == passes else done[level + 1], level)
            for key in (level, "grey", "grey²") if level == passes else (level,):
                if key in self.sums:
                    first = min(first, self.sums[key][0])
            if level == 0:
                first = min(first, emitted - OBJECT_REACH, done[passes])
            readers.append(min(first, guard))
        frames = self.frames
        for j in [j for j in frames if j < max(*readers, emitted)]:
            frame = frames[j]
            if j < emitted - OBJECT_REACH:  # read by its next round, its own output and the next outputs' objects
                frame.bwd_flows_px = []  # (1080p: 8.3 MB a frame)
            if j < readers[0]:
                frame.raw = None
            for level in range(1, passes + 1):
                if j < readers[level] and len(frame.warped) >= level:
                    frame.warped[level - 1] = None
                    if level == passes:
                        frame.prepared = frame.spread_grey = None
            if frame.raw is None and len(frame.warped) == passes and all(w is None for w in frame.warped):
                del frames[j]
        self.buffered = sum((f.raw is not None) + sum(w is not None for w in f.warped) for f in frames.values())
