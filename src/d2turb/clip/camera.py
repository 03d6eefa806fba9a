"""The camera of a clip (issue 49): its motion from frame to frame (shake, jumps), the canvas the frames are
registered on, and each output's return to its frame's camera pose (``ClipRestorer(stabilise=True)``, the default;
docs/clips.md, step 0 and "Back to the camera"). Arrays are numpy, as in ``clip.registration``."""

from __future__ import annotations

import collections
from dataclasses import dataclass

import cv2
import numpy as np

from d2turb.clip.registration import pixel_grid, remap, shift_flow, shrunk, shrunk_shift_px

# _POSE: the output's camera pose is the median of the global shifts of the frames within _POSE_HALF of it, each first
# moved to the output's time by its window's median velocity (the median of the frame-to-frame steps): a pan is
# followed, a jump stays a jump, switching at its frame, and the turbulence's whole-frame tilt, which moves small crops
# by several px from frame to frame and no clip can tell from a shake, is damped. Over the whole window the median left
# dost_street_clip's frame 2, four frames before a 55-px jump, some 40 px from its own view. The fused frame is moved
# there by bicubic interpolation (a whole-pixel pose kept the canvas's own sub-pixel offset, the first frames' mean
# tilt: 0.8x the plain mean's error on a zero-mean warp test)
_POSE_HALF = 2
_REPLICATE_PX = 1.0  # px of an edge replicated into the canvas that still count as seen
_BORDER_RAMP_PX = 8  # the fusion fades into the single frame over this many px inside the window's common view


class CameraTrack:
    """A clip's camera motion (``ClipRestorer(stabilise=True)``): each frame's global shift (phase correlation)
    against the mean of the frames placed before it (the last ``memory``, at a reduced size) is its pose g_i on the
    canvas, ``frame_i(x + g_i) ≈ canvas(x)``; the canvas is the first frame's view, so a shake of ±5 % and its jumps
    stay on it. Against a mean rather than the frame before, the errors do not add up along the clip (strong
    turbulence moves a small crop's frames by pixels, and a chain of frame-to-frame shifts wandered by up to 9 px in
    12 frames). ``shifts`` holds each frame's refined pose, the median of its last registration round's flow onto its
    canvas reference, from which the outputs take theirs."""

    def __init__(self, memory: int):
        self.poses: dict[int, tuple[float, float]] = {}
        self.shifts: dict[int, tuple[float, float]] = {}
        self._placed: collections.deque = collections.deque(maxlen=memory)  # reduced greys on the canvas
        self._sum = None  # their float32 sum

    def place(self, index: int, gray: np.ndarray) -> np.ndarray:
        """The frame's grey (H,W) uint8 moved onto the canvas, (H,W,1) uint8 (edges replicated)."""
        small, scale = shrunk(gray)
        pose = (0.0, 0.0)
        if self._placed:
            pose = shrunk_shift_px(self._sum / np.float32(len(self._placed)), small, scale)
        self.poses[index] = pose
        if pose != (0.0, 0.0):
            placed = remap(small, shift_flow(small.shape, pose[0] * scale, pose[1] * scale), consume=True)
        else:
            placed = small
        if len(self._placed) == self._placed.maxlen:
            self._sum -= self._placed[0]
        self._sum = placed.copy() if self._sum is None else self._sum + placed
        self._placed.append(placed)
        if pose == (0.0, 0.0):
            return gray[..., None]
        return remap(gray[..., None], shift_flow(gray.shape, *pose), consume=True)

    def output_pose(self, index: int, window: list[int], shape: tuple[int, int]) -> OutputPose:
        """Output ``index``'s pose (see ``_POSE``) and the part of the canvas every frame of its window sees;
        forgets the frames no later output reads."""
        poses = np.array([self.shifts.get(j, self.poses[j]) for j in window])
        velocity = np.median(np.diff(poses, axis=0), axis=0) if len(window) > 1 else np.zeros(2)
        near = [k for k, j in enumerate(window) if abs(j - index) <= _POSE_HALF]
        lag = np.array([window[k] - index for k in near], dtype=np.float64)
        median = np.median(poses[near] - lag[:, None] * velocity, axis=0)
        h, w = shape
        # canvas x is seen by frame j where 0 <= x + g_j <= w - 1: the window's common view; an edge replicated by
        # less than _REPLICATE_PX (the turbulence's own global jitter) is taken as seen
        x0, y0 = np.ceil(np.maximum(-poses.min(axis=0) - _REPLICATE_PX, 0)).astype(int)
        x1, y1 = np.floor(np.minimum([w - 1, h - 1] - poses.max(axis=0) + _REPLICATE_PX, [w - 1, h - 1])).astype(int)
        for j in [j for j in self.poses if j < window[0]]:
            del self.poses[j]
            self.shifts.pop(j, None)
        pose = (float(median[0]), float(median[1]))
        return OutputPose(pose, (x0, y0, x1, y1), self.shifts.get(index, self.poses[index]))


@dataclass
class OutputPose:
    """Moves a fused frame from the canvas to an output's camera pose ``(dx, dy)``
    (``output(y) = canvas(y − pose)``): what falls outside the canvas, or outside the ``common`` view
    ``(x0, y0, x1, y1)`` (inclusive, canvas px) of the window's frames, is taken from the frame itself (share 1),
    fading in over ``_BORDER_RAMP_PX``."""

    shift: tuple[float, float]
    common: tuple[int, int, int, int]
    frame_shift: tuple[float, float]  # the frame's own pose on the canvas

    def frame_at_output(self, raw: np.ndarray) -> np.ndarray:
        """The frame (H,W,C) as held, resampled to the output's pose: ``frame(y + g − pose)`` (bilinear)."""
        dx, dy = self.frame_shift[0] - self.shift[0], self.frame_shift[1] - self.shift[1]
        if abs(dx) < 1e-3 and abs(dy) < 1e-3:
            return raw
        return remap(raw, shift_flow(raw.shape[:2], dx, dy), consume=True)

    def apply(self, fused: np.ndarray, share: np.ndarray, flow: np.ndarray):
        """(fused (H,W,C), moving-object share (H,W), flow (H,W,2)) on the canvas → the same at the output's pose."""
        h, w = share.shape
        x0, y0, x1, y1 = self.common
        # the share of the fusion: 1 inside the common view, falling to 0 over the ramp towards its edges
        ramp = float(_BORDER_RAMP_PX)
        xs, ys = np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32)
        if (x0, y0, x1, y1) != (0, 0, w - 1, h - 1):
            wx = np.clip(np.minimum(_ramp(xs - x0, x0 > 0), _ramp(x1 - xs, x1 < w - 1)) / ramp, 0, 1)
            wy = np.clip(np.minimum(_ramp(ys - y0, y0 > 0), _ramp(y1 - ys, y1 < h - 1)) / ramp, 0, 1)
            share = 1 - (1 - share) * (wy[:, None] * wx[None, :])
        dx, dy = self.shift
        if abs(dx) < 1e-3 and abs(dy) < 1e-3:
            return fused, share, flow
        maps = shift_flow((h, w), -dx, -dy)
        maps += pixel_grid((h, w))
        out = cv2.remap(fused, maps, None, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE).reshape(fused.shape)
        # off the canvas the frame itself is used (share 1), moved by its own pose less the output's
        out_share = cv2.remap(share, maps, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=1.0)
        # frame(y − pose + flow(y − pose)) ≈ canvas(y − pose) = output(y)
        out_flow = cv2.remap(flow.astype(np.float32), maps, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out_flow -= np.array([dx, dy], dtype=np.float32)
        off = out_share >= 1.0
        out_flow[off] = (self.frame_shift[0] - dx, self.frame_shift[1] - dy)
        return out, out_share, out_flow.astype(flow.dtype)


def _ramp(inside_px: np.ndarray, edge: bool) -> np.ndarray:
    """Distance inside an uncovered ``edge`` (+1, so its first covered pixel fades in), or no fade without one."""
    return inside_px + 1 if edge else np.full_like(inside_px, np.inf)


__all__ = ["CameraTrack", "OutputPose"]
