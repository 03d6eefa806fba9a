"""The stages of the clip room, each a function of the clip's :class:`~d2turb.clip.state.ClipState`: a frame's
registration round (:func:`register`), an output's assembly (:func:`output_job`: the fusion, the moving-object
fallback, the return to the camera pose) and the fallback's share (:func:`fallback_share`). What runs when, and in
which thread, is :mod:`d2turb.clip.schedule`'s."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import cv2
import numpy as np
import torch

from d2turb.clip.frames import STORE_DTYPE, ClipFrame, as_float, image_of
from d2turb.clip.registration import global_shift_px, remap, shift_flow, to_gray_u8
from d2turb.clip.state import ClipState

_FALLBACK_BOX = 15  # px: residuals are averaged over this box before the moving-object test
_FALLBACK_LOW, _FALLBACK_HIGH = 3.0, 6.0  # in units of the frame's robust residual scale: blend from → to
_CHANNEL_MEAN = {c: np.full((1, c), 1 / c, np.float32) for c in (2, 3, 4)}  # cv2.transform: the mean over channels


def _now(call: Callable):
    return call()


def register(state: ClipState, index: int, k: int, submit: Callable = _now) -> None:
    """Registration round ``k`` of frame ``index``: its dense backward flow onto the mean of round k − 1 over its
    window (started from the global shift at round 1, when the camera is followed, and from round k − 1's flow after),
    the frame unwarped. After the last round the fusion prepares what it reads (``submit``: now or in its thread)."""
    frame = state.frames[index]
    ref_gray = to_gray_u8(state.reference(index, k - 1))
    if k == 1:
        init = (
            shift_flow(frame.gray.shape, *global_shift_px(ref_gray, frame.gray)) if state.camera is not None else None
        )
    else:
        init = frame.bwd_flows_px[-1]
    bwd_flow_px = state.flow_solver(ref_gray, frame.gray, init)
    # held as float16 (1080p: 8.3 MB instead of 16.6 a frame, up to two windows of them; 0.004 px resolution below
    # 8 px): it starts the next round's search and becomes the output's bwd_flow_px (float32 again)
    frame.bwd_flows_px = [cv2.multiply(bwd_flow_px, 1.0, dtype=cv2.CV_16F)]  # as numpy's astype, in a third of its time
    if k == state.passes and state.camera is not None:  # the pose, to the dense flow's accuracy: its median
        step = max(1, int(math.sqrt(bwd_flow_px.shape[0] * bwd_flow_px.shape[1] / 65536)))  # about 65k pixels read
        state.camera.shifts[index] = tuple(float(v) for v in np.median(bwd_flow_px[::step, ::step].reshape(-1, 2), 0))
    if k < state.passes:  # uint8 in, uint8 out (cv2.remap rounds); the float32 flow is no longer needed
        frame.warped.append(remap(frame.gray[..., None], bwd_flow_px, consume=True))
        return
    if frame.raw.dtype == np.uint8:
        frame.warped.append(remap(frame.raw, bwd_flow_px, consume=True))
    else:
        frame.warped.append(remap(frame.raw, bwd_flow_px, consume=True).astype(STORE_DTYPE))
    state.fusion.prepare(frame, [state.frames[j] for j in state.window(index)], k - 1, submit)


def output_job(state: ClipState, index: int, fallback: bool, submit: Callable | None = None) -> Callable[[], ClipFrame]:
    """Output ``index`` as a call that makes its :class:`ClipFrame` (it holds its own references to what it reads, so
    it may run in another thread while the next frames register). ``submit``: where the moving-object share of a
    threaded fusion is made beside it (None: in the call)."""
    fusion = state.fusion
    window = {j: state.frames[j] for j in state.window(index)}
    mean = state.reference(index, state.passes) if fusion.reads_mean else None
    fused = fusion.fuse(window, mean)
    against = mean if fusion.moving_against_mean else None  # what moving objects are found against (None: the fusion)
    frame = state.frames[index]
    share = None
    if fallback and submit is not None:
        share = submit(functools.partial(fallback_share, frame.warped[-1], against))
    pose = None
    if state.camera is not None:
        pose = state.camera.output_pose(index, list(window), frame.gray.shape)
    return functools.partial(
        finish, index, fused, against, frame.warped[-1], frame.raw, frame.bwd_flows_px[-1], fallback, share, pose
    )


def finish(index: int, fused, against, warped, raw, bwd_flow_px, fallback: bool, share=None, pose=None) -> ClipFrame:
    """The output frame from its fusion (an array, or a call that fuses), the moving-object fallback (``share``: a
    Future of it, or None to compute it here against ``against``, or the fusion when None), the frame's own images
    and the output's camera pose (a :class:`~d2turb.clip.camera.OutputPose`, None when the camera is not followed)."""
    fused = fused if isinstance(fused, np.ndarray) else fused()
    blend = np.zeros(fused.shape[:2], dtype=np.float32)
    if fallback:
        blend = fallback_share(warped, fused if against is None else against) if share is None else share.result()
    if pose is not None:
        fused, blend, bwd_flow_px = pose.apply(fused, blend, bwd_flow_px)
        if blend.any():  # the frame's own pixels moved by what its pose differs from the output's (sub-pixel)
            raw = pose.frame_at_output(raw)
    rows = np.flatnonzero(blend.any(axis=1))
    if rows.size:  # fused + blend·(image − fused) on the rows the fallback touches (fused is this output's own)
        part = slice(rows[0], rows[-1] + 1)
        step = np.subtract(image_of(raw[part]), fused[part])
        step *= blend[part, :, None]
        fused[part] += step
    # (3,H,W) as a view of the (H,W,3) array; a deblur gets a contiguous copy (ClipRestorer._deblur_jobs)
    fused = np.clip(fused, 0, 1, out=fused)
    fused_t = torch.from_numpy(fused).permute(2, 0, 1)
    camera = None if pose is None else tuple(float(v) for v in pose.frame_shift)
    share = torch.from_numpy(blend.astype(np.float32, copy=False))  # float64 where the pose's border ramp made it
    return ClipFrame(index, fused_t, fused_t, bwd_flow_px, share, camera_px=camera)


def fallback_share(warped: np.ndarray, fused: np.ndarray) -> np.ndarray:
    """Share of the single frame per pixel: 0 where the registered frame ``warped`` (as held: uint8, or float) agrees
    with the fusion within a few robust scales of its residual (box-averaged), rising to 1 where it stays far above (a
    moving object). On frames of ≥ 1 MP the box average is taken at half resolution (the box and the dilation span
    15 px: the decision is smooth at that scale) and the robust scale from every 4th residual."""
    diff = cv2.absdiff(as_float(warped), fused)  # OpenCV: a quarter of numpy's time at 1080p
    if diff.ndim == 2 or diff.shape[2] == 1:  # one channel (OpenCV drops a single channel's axis)
        r = diff.reshape(diff.shape[:2])
    else:
        r = cv2.transform(diff, _CHANNEL_MEAN[diff.shape[2]]).reshape(diff.shape[:2])
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
