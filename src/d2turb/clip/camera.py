"""The camera of a clip (issue 49): its motion from frame to frame (shake, jumps), the canvas the frames are
registered on, and each output's return to its frame's camera pose (``ClipRestorer(stabilise=True)``, the default;
docs/clips.md, step 0 and "Back to the camera"). Arrays are numpy, as in ``clip.registration``."""

from __future__ import annotations

import collections
from dataclasses import dataclass

import cv2
import numpy as np

from d2turb.clip.registration import MIN_SIDE_PX, DenseFlow, shift_maps, shifted, shrunk, shrunk_shift_px

# _POSE: the output's camera pose is the mean of its window's frames' global shifts: the window-mean geometry, which is
# the scene's for a still camera (the turbulence's whole-frame tilt is zero-mean; it moves small crops by several px
# from frame to frame and no clip can tell it from a shake), and a steady pan's middle frame. The demo's clips (no
# offset removed) scored +5.0 / +2.1 / +1.2 dB with it against +4.5 / +2.0 / −0.1 with the median (a drifting tilt)
# and +5.0 / −0.6 / +1.0 with the median of the frames within 2, moved by the window's median velocity. Near a jump the
# window's pose is between its sides (dost_street_clip's frame 2, four frames before a 55-px jump, landed some 40 px
# from its own view): there the frames within _POSE_HALF decide. The fused frame is moved by bicubic interpolation.
_POSE_HALF = 2
# ... the frames within _POSE_HALF are used only when their median leaves the window's by more than _POSE_OUTLIER
# robust spreads and _POSE_MIN_PX (a jump, a clip's end): a still camera's output keeps its window's mean
# geometry, which is the scene's (the turbulence's tilt is zero-mean; following each frame's neighbours put its
# whole-frame tilt into the output: the demo's strong clip fell to the input's PSNR, no offset removed). _POSE_MIN_PX 6,
# not 3: the strongest blind test clips' whole-frame tilt drifts by 3 px rms in small steps, and their frames' median
# left the window's by 3-6 px: followed, two of them lost 1.1 dB; the field validation clips' mean gain is the same
# with 6 (+0.37 / +1.49 / +0.52 dB against +0.39 / +1.30 / +0.68 with 3: their jumps and pans reach 5-13 px)
_POSE_OUTLIER, _POSE_MIN_PX = 3.0, 6.0
# ... and the output stays within _POSE_FROM_OWN_PX of its own frame's pose on each axis: a window that straddles a
# jump (or two) put the output 5-9 px from its frame's view, a frame whose truth it no longer matched (field
# validation clips 16 and 17: 16-19 dB against the input frame's 21-24 on those frames, offset removed)
_POSE_FROM_OWN_PX = 3.0
# frames are placed at this size: the median of a DIS flow there, not phase correlation, which a dark square moving
# 8 px a frame over a blurred scene dragged along (its poses wandered by 100 px in 12 frames)
_PLACE_SIDE_PX = 256
_REPLICATE_PX = 4.0  # px of an edge replicated into the canvas that still count as seen (see output_pose)
_BORDER_RAMP_PX = 8  # the fusion fades into the single frame over this many px inside the window's common view


class CameraTrack:
    """A clip's camera motion (``ClipRestorer(stabilise=True)``): each frame's global shift (the median of a dense
    flow at ≤ 256 px) against the mean of the frames placed before it (the last ``memory``, at that size) is its
    pose g_i on the canvas, ``frame_i(x + g_i) ≈ canvas(x)``; the canvas is the first frame's view, so a shake of
    ±5 % and its jumps stay on it. Against a mean rather than the frame before, the errors do not add up along the
    clip (strong turbulence moves a small crop's frames by pixels, and a chain of frame-to-frame shifts wandered by
    up to 9 px in 12 frames). ``shifts`` holds each frame's refined pose, the median of its last registration
    round's flow onto its canvas reference, from which the outputs take theirs."""

    def __init__(self, memory: int):
        self.poses: dict[int, tuple[float, float]] = {}
        self.shifts: dict[int, tuple[float, float]] = {}
        self._placed: collections.deque = collections.deque(maxlen=memory)  # reduced greys on the canvas
        self._sum = None  # their float32 sum
        self._flow = DenseFlow("medium")

    def place(self, index: int, gray: np.ndarray) -> np.ndarray:
        """The frame's grey (H,W) uint8 moved onto the canvas, (H,W,1) uint8 (edges replicated)."""
        small, scale = shrunk(gray, _PLACE_SIDE_PX)
        pose = (0.0, 0.0)
        if self._placed:
            ref = self._sum / np.float32(len(self._placed))
            if min(small.shape) >= MIN_SIDE_PX:  # the median of a dense flow: a moving object is outvoted
                u8 = [np.clip(x + 0.5, 0, 255).astype(np.uint8) for x in (ref, small)]
                bwd_flow_px = self._flow(u8[0], u8[1])
                pose = tuple(float(v) / scale for v in np.median(bwd_flow_px.reshape(-1, 2), axis=0))
            else:
                pose = shrunk_shift_px(ref, small, scale)
        self.poses[index] = pose
        if pose != (0.0, 0.0):
            placed = shifted(small, pose[0] * scale, pose[1] * scale)
        else:
            placed = small
        if len(self._placed) == self._placed.maxlen:
            self._sum -= self._placed[0]
        self._sum = placed.copy() if self._sum is None else self._sum + placed
        self._placed.append(placed)
        if pose == (0.0, 0.0):
            return gray[..., None]
        return shifted(gray[..., None], *pose)

    def output_pose(self, index: int, window: list[int], shape: tuple[int, int]) -> OutputPose:
        """Output ``index``'s pose (see ``_POSE``) and the part of the canvas every frame of its window sees;
        forgets the frames no later output reads."""
        poses = np.array([self.shifts.get(j, self.poses[j]) for j in window])
        pose = poses.mean(axis=0)
        near = np.median(poses[[k for k, j in enumerate(window) if abs(j - index) <= _POSE_HALF]], axis=0)
        # the frame-to-frame jitter's robust scale (about the poses' own spread it missed dost_street_clip's jump: the
        # window's two sides made that spread 15 px, and frame 2 landed 48 px from its own view)
        steps = np.abs(np.diff(poses, axis=0)) if len(window) > 1 else np.zeros((1, 2))
        spread = 1.4826 * np.median(steps, axis=0) / np.sqrt(2)
        if np.any(np.abs(near - pose) > np.maximum(_POSE_OUTLIER * spread, _POSE_MIN_PX)):
            pose = near  # the camera moved (a jump): the frames around the output, not the window
        own = np.array(self.shifts.get(index, self.poses[index]))
        pose = own + np.clip(pose - own, -_POSE_FROM_OWN_PX, _POSE_FROM_OWN_PX)  # never far from the frame's own view
        h, w = shape
        # canvas x is seen by frame j where 0 <= x + g_j <= w - 1: the window's common view; an edge replicated by
        # less than _REPLICATE_PX (the turbulence's own global jitter) is taken as seen
        x0, y0 = np.ceil(np.maximum(-poses.min(axis=0) - _REPLICATE_PX, 0)).astype(int)
        x1, y1 = np.floor(np.minimum([w - 1, h - 1] - poses.max(axis=0) + _REPLICATE_PX, [w - 1, h - 1])).astype(int)
        for j in [j for j in self.poses if j < window[0]]:
            del self.poses[j]
            self.shifts.pop(j, None)
        pose = (float(pose[0]), float(pose[1]))
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

    def apply(self, fused: np.ndarray, share: np.ndarray, bwd_flow_px: np.ndarray):
        """(fused (H,W,C), moving-object share (H,W), the frame's backward flow (H,W,2) px) on the canvas → the same at
        the output's pose."""
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
            return fused, share, bwd_flow_px
        maps = shift_maps((h, w), -dx, -dy)
        replicate = cv2.BORDER_REPLICATE
        if fused.dtype == np.float32 and fused.ndim == 3 and fused.shape[2] in (1, 3):
            out = _shifted(fused, -dx, -dy, cv2.INTER_CUBIC).reshape(fused.shape)
        else:
            out = cv2.remap(fused, maps, None, cv2.INTER_CUBIC, borderMode=replicate).reshape(fused.shape)
        # off the canvas the frame itself is used (share 1), moved by its own pose less the output's
        out_share = cv2.remap(share, maps, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=1.0)
        # frame(y − pose + flow(y − pose)) ≈ canvas(y − pose) = output(y)
        flow32 = bwd_flow_px.astype(np.float32, copy=False)  # read only
        if _off_half_step(-dx) and _off_half_step(-dy):
            out_flow = _shifted(flow32, -dx, -dy, cv2.INTER_LINEAR)
        else:
            out_flow = cv2.remap(flow32, maps, None, cv2.INTER_LINEAR, borderMode=replicate)
        off = out_share >= 1.0
        # axis by axis (a last axis of 2 is numpy's slowest loop: 11 and 23 ms against 4 and 16 at 1080p)
        for k, (s, g) in enumerate(zip(self.shift, self.frame_shift)):
            out_flow[..., k] -= np.float32(s)
            out_flow[..., k][off] = g - s
        return out, out_share, out_flow.astype(bwd_flow_px.dtype, copy=False)


def _shifted(image: np.ndarray, dx: float, dy: float, interpolation: int) -> np.ndarray:
    """``image(x + dx, y + dy)``, edges replicated: ``cv2.warpAffine``, no full-size maps (1080p bicubic RGB: 31 ms
    against 88 with the maps and ``cv2.remap``). Equal to the bit to ``cv2.remap`` on ``pixel_grid + shift_flow``
    (both quantise the position to 1/32 px) for INTER_CUBIC on one or three float32 channels (OpenCV 5.1: every
    shift k/128 px within ±64 px on either axis); for INTER_LINEAR on two float32 channels off the half-steps only
    (``_off_half_step``); OpenCV 5's own INTER_LINEAR kernels for one float32 channel and for uint8 are not
    (benchmarks/RESULTS.md, 2026-12-08)."""
    h, w = image.shape[:2]
    m = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]])
    flags = interpolation | cv2.WARP_INVERSE_MAP
    return cv2.warpAffine(image, m, (w, h), flags=flags, borderMode=cv2.BORDER_REPLICATE)


def _off_half_step(shift_px: float) -> bool:
    """Whether ``cv2.warpAffine`` (the shift rounded to 1/1024 px, then to 1/32) and ``cv2.remap`` (x + shift in
    float32, then to 1/32) round a shift to the same 1/32 px: true unless it lies within 1/640 px of a half step
    (they differed within 1/2048 px of one)."""
    frac = (abs(float(np.float32(shift_px))) * 32.0) % 1.0
    return abs(frac - 0.5) > 0.05


def _ramp(inside_px: np.ndarray, edge: bool) -> np.ndarray:
    """Distance inside an uncovered ``edge`` (+1, so its first covered pixel fades in), or no fade without one."""
    return inside_px + 1 if edge else np.full_like(inside_px, np.inf)


__all__ = ["CameraTrack", "OutputPose"]
