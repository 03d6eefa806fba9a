"""The live preset's stream state (:class:`LiveState`, used by :class:`~d2turb.clip.live.LiveRestorer`): the frames and
registrations a window still reads, the running sums, how far each step has come; its registration (DIS per round,
the flow upsampled) and its output frames (:class:`LiveFrame`: the flow upsampled when read)."""

from __future__ import annotations

from collections.abc import Iterator

import cv2
import numpy as np
import torch

from d2turb.clip.frames import ClipFrame, window_span
from d2turb.clip.registration import DenseFlow, check_registrable, pixel_grid, remap, to_gray_u8, to_hwc
from d2turb.device import usable_cores
from d2turb.errors import D2TurbError

LIVE_ROUNDS = 2  # DIS calls a frame (the second against the first round's mean; docs/clips.md)
LIVE_SCALE = 0.5  # registration at half size (docs/clips.md, "The live preset": what quarter size lost)
# DIS per registration round: None, OpenCV's ultrafast preset; else (finest scale, patch size, patch stride, gradient
# descent iterations, variational refinement iterations) on the image at LIVE_SCALE (docs/clips.md, "The live preset":
# what each choice cost and lost on the blind test set)
# per round: the reference window centred on the frame (W(i)) or the N frames up to it. Round 1's sets the outputs'
# geometry: behind the frame, the blind set's first 6 clips lost 0.41 dB of plain PSNR (the mean tilt of the frames
# before it, a global offset the offset-removed PSNR does not count: +0.06 dB there); centred, 0.14 (+0.04); both
# centred, 0.03 (-0.04) at 1.5 windows of latency instead of one (docs/clips.md, "The live preset")
LIVE_CENTRED = [True, False]
# round 2 without the variational refinement: 90 against 102–109 CPU ms a frame at 720p (240 frames, near-idle),
# −0.04 / −0.14 / −0.09 dB on the blind set (docs/clips.md, "The live preset")
LIVE_DIS = [None, (0, 8, 6, 12, 0)]


def live_flow_solver(k: int = 1) -> cv2.DISOpticalFlow:
    """OpenCV's DIS of registration round ``k`` (``LIVE_DIS``), with mean normalisation (robust to the brightness
    flicker of scintillation)."""
    cfg = LIVE_DIS[k - 1]
    if cfg is None:
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST)
    else:
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        fs, ps, st, gd, vi = cfg
        dis.setFinestScale(fs)
        dis.setPatchSize(ps)
        dis.setPatchStride(st)
        dis.setGradientDescentIterations(gd)
        dis.setVariationalRefinementIterations(vi)
    dis.setUseMeanNormalization(True)
    return dis


def upsampled_flow(flow_small: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A flow (h,w,2) in px of the small image → (H,W,2) float32 in px of the full one: bilinear (pixel centres
    aligned, as ``cv2.resize`` places them), each component times the size ratio of its axis."""
    h, w = shape
    up = cv2.resize(flow_small, (w, h), interpolation=cv2.INTER_LINEAR)
    up[..., 0] *= np.float32(w / flow_small.shape[1])
    up[..., 1] *= np.float32(h / flow_small.shape[0])
    return up


def upsampled_maps(flow_small: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``pixel_grid(shape) + upsampled_flow(flow_small, shape)`` (the absolute coordinates ``cv2.remap`` reads) in one
    full-size pass: the small image's own coordinates in full-size px, (x + ½)/s − ½, plus its flow in full-size px,
    upsampled bilinearly (a linear grid is reproduced exactly), then the outermost rows and columns, where
    ``cv2.resize`` repeats the edge, moved by the half pixel of their place (size ratios under 3; else two steps)."""
    h, w = shape
    hs, ws = flow_small.shape[:2]
    rx, ry = np.float32(w / ws), np.float32(h / hs)
    if max(rx, ry) >= 3:  # cv2.resize repeats the edge over more than one full-size pixel: the two steps
        return np.add(upsampled_flow(flow_small, shape), pixel_grid(shape))
    small = np.empty_like(flow_small, dtype=np.float32)
    small[..., 0] = flow_small[..., 0] * rx + ((np.arange(ws, dtype=np.float32) + np.float32(0.5)) * rx - 0.5)
    small[..., 1] = flow_small[..., 1] * ry + ((np.arange(hs, dtype=np.float32) + np.float32(0.5)) * ry - 0.5)[:, None]
    maps = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
    edge_x, edge_y = np.float32((rx - 1) / 2), np.float32((ry - 1) / 2)  # the edge's repeated value less its own
    maps[:, 0, 0] -= edge_x
    maps[:, -1, 0] += edge_x
    maps[0, :, 1] -= edge_y
    maps[-1, :, 1] += edge_y
    return maps


class _Sum:
    """A running sum of (H,W,C) images over a sliding window: ``add`` the newest, ``take`` the oldest off. 8-bit
    images are summed exactly in integers (uint16 while 257 frames cannot overflow it, else int32), others in
    float64."""

    def __init__(self, like: np.ndarray, temporal: int):
        if like.dtype == np.uint8:
            self.dtype, self.cv = (np.uint16, cv2.CV_16U) if temporal <= 257 else (np.int32, cv2.CV_32S)
        else:
            self.dtype, self.cv = np.float64, cv2.CV_64F
        self.total = np.zeros(like.shape, self.dtype)
        self.count = 0

    def add(self, image: np.ndarray) -> None:
        cv2.add(self.total, image, dst=self.total, dtype=self.cv)
        self.count += 1

    def take(self, image: np.ndarray) -> None:
        cv2.subtract(self.total, image, dst=self.total, dtype=self.cv)
        self.count -= 1

    def mean(self, scale: float = 1.0) -> np.ndarray:
        """The mean times ``scale``, float32."""
        out = np.empty(self.total.shape, np.float32)
        np.multiply(self.total, np.float32(scale / self.count), out=out, casting="unsafe")
        return out


class LiveState:
    """One stream's state: what a window still reads (per frame: its small grey, its first-round registration, the
    frame, its last-round registration and flow), the running sums, how far each step has come."""

    def __init__(self, restorer):
        self.n, self.rounds, self.scale = restorer.temporal, restorer.rounds, restorer.scale
        # levels[k][i]: frame i's small grey (k = 0) or its round-k registration (k < rounds), (h,w,1) uint8
        self.levels: list[dict[int, np.ndarray]] = [{} for _ in range(self.rounds)]
        self.init: dict[int, np.ndarray] = {}  # i → the small flow of its round before the last (two rounds)
        self.raw: dict[int, np.ndarray] = {}  # i → the frame (H,W,C), until its last round
        self.warped: dict[int, np.ndarray] = {}  # i → the frame registered, while an output window holds it
        self.flows: dict[int, np.ndarray] = {}  # i → its last round's small flow, until its output
        self.ref_sums: list = [None] * self.rounds  # per round: running sum of its reference window's level
        self.ref_span = [[0, 0] for _ in range(self.rounds)]  # ... the frames [lo, hi) in it
        self.out_sum: _Sum | None = None
        self.out_span = [0, 0]
        self.done = [0] * (self.rounds + 1)  # frames read (0), registered in round k (k)
        self.emitted = 0
        self.length: int | None = None
        self.shape: tuple | None = None
        self.dis = [live_flow_solver(k) for k in range(1, self.rounds + 1)]
        cv2.setNumThreads(usable_cores())

    def outputs(self, source: Iterator) -> Iterator[ClipFrame]:
        """The fused outputs in order, each as soon as its window is registered."""
        for item in source:
            self._hold(item)
            yield from self._advance()
        self.length = self.done[0]
        if self.length < 2:
            raise D2TurbError(f"a clip needs at least 2 frames, got {self.length}")
        yield from self._advance()

    # -- windows ---------------------------------------------------------------------------------------------------
    def _ref_window(self, i: int, k: int = 1) -> tuple[int, int]:
        """[lo, hi) of frame i's reference window in round k: centred on it as W(i) where ``LIVE_CENTRED[k - 1]``, else
        the N frames up to i (the first N frames: the first N)."""
        if LIVE_CENTRED[k - 1]:
            return self._out_window(i)
        hi = max(i + 1, self.n)
        if self.length is not None:
            hi = min(hi, self.length)
        return max(0, hi - self.n), hi

    def _ready(self, i: int, k: int) -> bool:
        """Whether round k of frame i can run: its reference window's level k − 1 is done."""
        return self._ref_window(i, k)[1] <= self.done[k - 1]

    def _out_window(self, t: int) -> tuple[int, int]:
        """[lo, hi) of output t's window W(t) (``window_span``: centred, shifted inward at the clip's ends)."""
        return window_span(t, self.n, self.length)

    def _advance(self) -> Iterator[ClipFrame]:
        """Every registration whose reference window is read (round by round), then every output whose window is
        registered; what no window reads any more is dropped."""
        end = self.length if self.length is not None else float("inf")
        for k in range(1, self.rounds + 1):
            while self.done[k] < min(self.done[k - 1], end) and self._ready(self.done[k], k):
                self._register(self.done[k], k)
                self.done[k] += 1
                self._release()
        while self.emitted < end and self._out_window(self.emitted)[1] <= self.done[self.rounds]:
            yield self._output(self.emitted)
            self.emitted += 1

    def _slide(self, total: _Sum, span: list, lo: int, hi: int, images: dict) -> None:
        """Move the running sum ``total`` of ``images`` over [span) to [lo, hi) (both ends only move forward)."""
        while span[1] < hi:
            total.add(images[span[1]])
            span[1] += 1
        while span[0] < lo:
            total.take(images[span[0]])
            span[0] += 1

    # -- steps -----------------------------------------------------------------------------------------------------
    def _hold(self, item) -> None:
        i = self.done[0]
        frame = item if isinstance(item, np.ndarray) and item.dtype == np.uint8 and item.ndim == 3 else to_hwc(item)
        frame = np.ascontiguousarray(frame)
        if self.shape is None:
            check_registrable(*frame.shape[:2])
            self.shape = frame.shape
            h, w = frame.shape[:2]
            self.small_size = (max(12, round(w * self.scale)), max(12, round(h * self.scale)))
        elif frame.shape != self.shape:
            raise D2TurbError(f"frame {i} is {frame.shape[1]}x{frame.shape[0]}, the clip's first is "
                              f"{self.shape[1]}x{self.shape[0]}: all frames must be of one size")  # fmt: skip
        self.raw[i] = frame
        grey = _luma_u8(frame)
        if i == 0:  # frame 0's flow onto its output is measured once more, finely (_output)
            self.first_grey = grey
        if self.small_size != (grey.shape[1], grey.shape[0]):
            grey = cv2.resize(grey, self.small_size, interpolation=cv2.INTER_AREA)
        self.levels[0][i] = grey.reshape(*grey.shape[:2], 1)
        self.done[0] += 1

    def _register(self, i: int, k: int) -> None:
        """Round k of frame i: its level k − 1 grey registered to the mean of that level over its reference window."""
        lo, hi = self._ref_window(i, k)
        level = self.levels[k - 1]
        if self.ref_sums[k - 1] is None:
            self.ref_sums[k - 1] = _Sum(level[i], self.n)
        total, span = self.ref_sums[k - 1], self.ref_span[k - 1]
        self._slide(total, span, lo, hi, level)
        reference = cv2.convertScaleAbs(total.total, alpha=1.0 / total.count)  # the mean, rounded, uint8
        grey = self.levels[0][i][..., 0]
        flow = self.dis[k - 1].calc(reference.reshape(grey.shape), grey, self.init.pop(i, None))
        if k < self.rounds:
            self.init[i] = flow
            self.levels[k][i] = remap(self.levels[0][i], flow)  # (h,w,1) uint8; the flow kept to start round k + 1
        else:
            self.flows[i] = flow
            maps = upsampled_maps(flow, self.shape[:2])
            out = cv2.remap(self.raw.pop(i), maps, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            self.warped[i] = out.reshape(self.shape)

    def _release(self) -> None:
        """Drop the greys that nothing reads any more: out of their round's reference sum, and (the small greys, which
        every round registers) once their frame's last round is done."""
        last = self.done[self.rounds]
        for m, level in enumerate(self.levels):
            lo = self.ref_span[m][0]
            for j in [j for j in level if j < lo and (m > 0 or j < last)]:
                del level[j]

    def _output(self, t: int) -> ClipFrame:
        lo, hi = self._out_window(t)
        if self.out_sum is None:
            self.out_sum = _Sum(self.warped[lo], self.n)
        self._slide(self.out_sum, self.out_span, lo, hi, self.warped)
        for j in [j for j in self.warped if j < lo]:
            del self.warped[j]
        scale = 1 / 255 if self.out_sum.dtype != np.float64 else 1.0
        fused = torch.from_numpy(self.out_sum.mean(scale)).permute(2, 0, 1)
        flow = (self.flows.pop(t), self.shape[:2])  # upsampled when read (most callers never do)
        if t == 0:
            flow = self._first_flow(fused)
        return LiveFrame(t, fused, fused, flow, _zeros(self.shape[:2]))

    def _first_flow(self, fused: torch.Tensor) -> np.ndarray:
        """Frame 0's backward flow onto its output, by DIS at the default's accuracy (``DenseFlow("fast")``, once a
        clip): what the blind deblur reads of the registered motion (its estimate of the blur grows with the tilt's
        spread, which the live registration's coarse flow reads short: the blind set lost up to 2 dB without it)."""
        grey = to_gray_u8(np.ascontiguousarray(fused.permute(1, 2, 0).numpy()))
        flow = DenseFlow("fast")(grey, self.first_grey)
        del self.first_grey
        return flow


class LiveFrame(ClipFrame):
    """A :class:`~d2turb.clip.ClipFrame` whose flow is held as the registration made it, at the registration's size,
    and upsampled to the frame's (:func:`upsampled_flow`, float32) when first read: built with ``bwd_flow_hwc_px`` =
    (small flow, (H, W)) or a full-size flow."""

    @property
    def bwd_flow_hwc_px(self) -> np.ndarray:
        if isinstance(self._flow, tuple):
            self._flow = upsampled_flow(*self._flow)
        return self._flow

    @bwd_flow_hwc_px.setter
    def bwd_flow_hwc_px(self, value) -> None:
        self._flow = value


def _luma_u8(frame: np.ndarray) -> np.ndarray:
    """(H,W) uint8 luma of an (H,W,C) frame: OpenCV's for 8-bit RGB (BT.601, rounded), else :func:`to_gray_u8`."""
    if frame.dtype == np.uint8:
        if frame.shape[2] == 3:
            return cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY)
        return np.ascontiguousarray(frame[..., 0])
    return to_gray_u8(frame)


_ZEROS: dict = {}


def _zeros(shape: tuple[int, int]) -> torch.Tensor:
    """A shared (H,W) float32 tensor of zeros: the live outputs' fallback share (none; read, never written)."""
    if shape not in _ZEROS:
        _ZEROS.clear()
        _ZEROS[shape] = torch.zeros(shape)
    return _ZEROS[shape]
