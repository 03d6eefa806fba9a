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

from d2turb.clip.frames import STORE_DTYPE, ClipFrame, as_float, channel_mean, image_of
from d2turb.clip.registration import global_shift_px, is_large_frame, pixel_grid, remap, shift_flow, to_gray_u8
from d2turb.clip.state import OBJECT_REACH, ClipState

_FALLBACK_BOX = 15  # px: residuals are averaged over this box before the moving-object test
_FALLBACK_LOW, _FALLBACK_HIGH = 3.0, 6.0  # in units of the frame's robust residual scale: blend from → to
_FILL_SIGMA_PX, _FILL_KNOWN, _FILL_MIN_WEIGHT = 32.0, 0.01, 0.05  # object_flow: spread, share of a known flow, and
# the blurred known weight below which the fill leans on the median
# spread_share: the window's grey variance (box-averaged) over what noise and registration explain, from k to 2k:
# chosen on 24 field validation clips (val_field24, docs/clips.md), default restore, offset-removed PSNR per bin:
# before (frame t's residual only) 22.34 / 21.63 / 21.12 dB, boxes −1.23 / −0.98 / −0.51 dB against the input; k = 3,
# 5, 8: 22.67 / 21.74 / 21.19, 22.73 / 21.73 / 21.23, 22.72 / 21.78 / 21.22 dB (boxes +0.12 / −0.06 / +0.38,
# +0.14 / −0.13 / +0.38, +0.06 / −0.18 / +0.27); 5 to 10 times the variance's median instead: 22.62 / 21.62 / 21.09
_SPREAD_K = 5.0
# ... and never below a spread of 4 grey levels (a clean clip's registered frames differ by interpolation alone: on
# it every edge would stand out)
_SPREAD_FLOOR = (4.0 / 255) ** 2
# object_average: the neighbours t ± 1 .. t ± _OBJECT_REACH averaged into the frame where it stands in, each weighted
# by exp(−(e / (_OBJECT_AGREE · s))²), e its box-averaged difference from frame t after alignment, s the median e
_OBJECT_AGREE = 2.0
_OBJECT_CENTRE_SIGMA = 2.0  # px: the smoothing of the mean-geometry correction
_OBJECT_FILL_REACH = 96  # px: a neighbour's flow is filled over the object's box grown by this (3σ of the fill)
_OBJECT_BOX = 7  # px: the disagreement is averaged over this box
_OBJECT_MARGIN = 16  # px: the aligned crop reaches this far beyond the share
_OBJECT_MAX_PX = 1 << 17  # px: the boxes averaged in one frame, at most (twice a 256² frame: a field clip's are all)


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
    bwd_flow_px = state.flow_solver_for(k)(ref_gray, frame.gray, init)
    # held as float16 (1080p: 8.3 MB instead of 16.6 a frame, up to two windows of them; 0.004 px resolution below
    # 8 px): it starts the next round's search and becomes the output's bwd_flow_px (float32 again)
    frame.bwd_flows_px = [cv2.multiply(bwd_flow_px, 1.0, dtype=cv2.CV_16F)]  # as numpy's astype, in a third of its time
    if k == state.passes and state.camera is not None:  # the pose, to the dense flow's accuracy: its median
        step = max(1, int(math.sqrt(bwd_flow_px.shape[0] * bwd_flow_px.shape[1] / 65536)))  # about 65k pixels read
        state.camera.shifts[index] = tuple(float(v) for v in np.median(bwd_flow_px[::step, ::step].reshape(-1, 2), 0))
    if k < state.passes:  # uint8 in, uint8 out (cv2.remap rounds); the float32 flow is no longer needed
        frame.warped.append(remap(frame.gray[..., None], bwd_flow_px, consume=True))
        return
    # what the fusion reads, bicubic: a frame resampled bilinearly at a fractional shift f keeps |1 − 2f| of its
    # Nyquist detail, and a window's mean averages that loss in (a shaken static scene, no turbulence: the mean 4–4.6
    # dB below its input frames with bilinear, above them with bicubic; docs/clips.md)
    warped = remap(frame.raw, bwd_flow_px, consume=True, interpolation=cv2.INTER_CUBIC)
    frame.warped.append(warped if frame.raw.dtype == np.uint8 else warped.astype(STORE_DTYPE))
    state.fusion.prepare(frame, [state.frames[j] for j in state.window(index, k - 1)], k - 1, submit)


def output_job(state: ClipState, index: int, fallback: bool, submit: Callable | None = None) -> Callable[[], ClipFrame]:
    """Output ``index`` as a call that makes its :class:`ClipFrame` (it holds its own references to what it reads, so
    it may run in another thread while the next frames register). ``submit``: where the moving-object share of a
    threaded fusion is made beside it (None: in the call)."""
    fusion = state.fusion
    window = {j: state.frames[j] for j in state.window(index, state.passes)}
    mean = state.reference(index, state.passes) if fusion.reads_mean else None
    fused = fusion.fuse(window, mean)
    against = mean if fusion.moving_against_mean else None  # what moving objects are found against (None: the fusion)
    frame = state.frames[index]
    share = None
    if fallback and submit is not None:
        share = submit(functools.partial(fallback_share, frame.warped[-1], against))
    spread = state.spread(index) if fallback else None
    pose = None
    if state.camera is not None:
        pose = state.camera.output_pose(index, list(window), frame.gray.shape)
    neighbours = None
    if fallback and OBJECT_REACH > 0:  # frames t ± 1 .. t ± OBJECT_REACH of the window: raw and last flow
        near = [(j, window[j]) for j in window if 0 < abs(j - index) <= OBJECT_REACH]
        neighbours = [(j - index, f.raw, f.bwd_flows_px[-1]) for j, f in near if f.raw is not None and f.bwd_flows_px]
    return functools.partial(
        finish,
        index,
        fused,
        against,
        frame.warped[-1],
        frame.raw,
        frame.bwd_flows_px[-1],
        fallback,
        share,
        pose,
        spread,
        neighbours,
    )


def finish(
    index: int,
    fused,
    against,
    warped,
    raw,
    bwd_flow_px,
    fallback: bool,
    share=None,
    pose=None,
    spread=None,
    neighbours=None,
) -> ClipFrame:
    """The output frame from its fusion (an array, or a call that fuses), the moving-object fallback (``share``: a
    Future of it, or None to compute it here against ``against``, or the fusion when None; with ``spread``, the
    window's (variance, mean) of :meth:`ClipState.spread`, the larger of it and :func:`spread_share`), the frame's own
    images and the output's camera pose (a :class:`~d2turb.clip.camera.OutputPose`, None when the camera is not
    followed)."""
    fused = fused if isinstance(fused, np.ndarray) else fused()
    blend = np.zeros(fused.shape[:2], dtype=np.float32)
    if fallback:
        blend = fallback_share(warped, fused if against is None else against) if share is None else share.result()
        if spread is not None:
            blend = np.maximum(blend, spread_share(*spread, blend.shape), out=blend)
    if pose is not None:
        fused, blend, bwd_flow_px = pose.apply(fused, blend, bwd_flow_px)
    rows = np.flatnonzero(blend.any(axis=1))
    if rows.size:  # fused + blend·(image − fused) on the rows the fallback touches (fused is this output's own)
        # the frame's own pixels registered by the flow around them (a moving object's own flow is not the air's)
        raw = remap(raw, object_flow(bwd_flow_px, blend), consume=True)
        part = slice(rows[0], rows[-1] + 1)
        own = image_of(raw[part])
        shift = (0.0, 0.0) if pose is None else pose.shift
        for box in _object_boxes(blend, part) if neighbours else []:  # smallest first, within _OBJECT_MAX_PX
            # the frames near t unwarped as it is, aligned onto its pixels, averaged where they agree
            y0, y1, x0, x1 = box
            near = [_unwarped(r, f, shift, blend, box) for _, r, f in neighbours]
            inside = (slice(y0 - part.start, y1 - part.start), slice(x0, x1))
            own[inside] = object_average(
                np.ascontiguousarray(own[inside]), near, blend[y0:y1, x0:x1], [d for d, _, _ in neighbours]
            )
        step = np.subtract(own, fused[part])
        step *= blend[part, :, None]
        fused[part] += step
    # (3,H,W) as a view of the (H,W,3) array; a deblur gets a contiguous copy (ClipRestorer._deblur_jobs)
    fused = np.clip(fused, 0, 1, out=fused)
    fused_t = torch.from_numpy(fused).permute(2, 0, 1)
    camera = None if pose is None else tuple(float(v) for v in pose.frame_shift)
    share = torch.from_numpy(blend.astype(np.float32, copy=False))  # float64 where the pose's border ramp made it
    return ClipFrame(index, fused_t, fused_t, bwd_flow_px, share, camera_px=camera)


def object_flow(bwd_flow_px: np.ndarray, share: np.ndarray) -> np.ndarray:
    """The frame's backward flow (H,W,2) px with what it reads where the frame stands in for the fusion (``share`` >
    0: a moving object, an uncovered border) filled from the flow around it, float32. There the dense flow matched the
    object against a reference it is not in; the air's tilt is smooth over tens of px, so the flow of the static
    scene around it, spread inward (a normalised Gaussian convolution of σ ``_FILL_SIGMA_PX`` at quarter resolution),
    unwarps the object's own pixels as the fusion's were (frame t unwarped by its true flow gains +0.9-1.2 dB inside
    the field clips' objects over the input frame; docs/clips_field_oracles.md). Far from any such flow, the median
    of the rest (the frame's global shift)."""
    flow = cv2.multiply(bwd_flow_px, 1.0, dtype=cv2.CV_32F)  # float32 (held as float16), a copy: filled in place
    h, w = share.shape
    unknown = share > _FILL_KNOWN
    if not unknown.any():
        return flow
    known = (share <= _FILL_KNOWN).astype(np.float32)
    if not known.any():
        return flow
    small = ((w + 3) // 4, (h + 3) // 4)
    k_small = cv2.resize(known, small, interpolation=cv2.INTER_AREA)
    f_small = cv2.resize(cv2.multiply(flow, cv2.merge([known, known])), small, interpolation=cv2.INTER_AREA)
    whole = k_small >= 1  # cells of known flow only: their mean flows, whose median is the rest's
    rest = np.median(f_small[whole] if whole.any() else flow[known > 0], axis=0).astype(np.float32)
    sigma = _FILL_SIGMA_PX / 4
    k_blur = cv2.GaussianBlur(k_small, (0, 0), sigma)
    f_blur = cv2.GaussianBlur(f_small, (0, 0), sigma)
    weight = np.clip(k_blur / _FILL_MIN_WEIGHT, 0, 1)[..., None]  # → the median where no known flow is near
    filled_small = weight * f_blur / np.maximum(k_blur, 1e-6)[..., None] + (1 - weight) * rest
    filled = cv2.resize(filled_small, (w, h), interpolation=cv2.INTER_LINEAR)
    np.copyto(flow, filled, where=unknown[..., None])
    return flow


def _object_boxes(share: np.ndarray, rows: slice) -> list[tuple[int, int, int, int]]:
    """(y0, y1, x0, x1) of each connected part of ``share`` > ``_FILL_KNOWN`` (found at quarter size), grown by
    ``_OBJECT_MARGIN`` and kept within ``rows``; boxes that overlap are merged (an uncovered border strip and an
    object far from it stay two boxes: one bounding box of both made a 1080p frame cost 2 s). Boxes under 16 px a
    side are left out (too small to register), and the largest ones beyond ``_OBJECT_MAX_PX`` in all (their pixels
    keep frame t alone: a 1080p frame whose share is scattered over the frame, as dost_street_clip's, merged into one
    box of the whole frame and made the default restore 4× slower)."""
    h, w = share.shape
    mask = (share > _FILL_KNOWN).astype(np.float32)
    small = (cv2.resize(mask, ((w + 3) // 4, (h + 3) // 4), interpolation=cv2.INTER_AREA) > 0).astype(np.uint8)
    count, _, stats, _ = cv2.connectedComponentsWithStats(small, connectivity=8)
    m = _OBJECT_MARGIN
    boxes = []
    for x, y, bw, bh, _ in stats[1:count]:
        boxes.append(
            [max(rows.start, 4 * y - m), min(rows.stop, 4 * (y + bh) + m), max(0, 4 * x - m), min(w, 4 * (x + bw) + m)]
        )
    merged = True
    while merged:  # until no two boxes overlap
        merged = False
        for a in range(len(boxes)):
            for b in range(a + 1, len(boxes)):
                p, q = boxes[a], boxes[b]
                if p[0] < q[1] and q[0] < p[1] and p[2] < q[3] and q[2] < p[3]:
                    boxes[a] = [min(p[0], q[0]), max(p[1], q[1]), min(p[2], q[2]), max(p[3], q[3])]
                    del boxes[b]
                    merged = True
                    break
            if merged:
                break
    kept, total = [], 0
    for b in sorted(boxes, key=lambda b: (b[1] - b[0]) * (b[3] - b[2])):
        area = (b[1] - b[0]) * (b[3] - b[2])
        if min(b[1] - b[0], b[3] - b[2]) >= 16 and total + area <= _OBJECT_MAX_PX:
            kept.append(tuple(int(v) for v in b))
            total += area
    return kept


def _unwarped(raw: np.ndarray, bwd_flow_px: np.ndarray, shift: tuple[float, float], share, box) -> np.ndarray:
    """A neighbour's raw frame unwarped as frame t's own pixels are, inside ``box`` (y0, y1, x0, x1): its flow onto
    the canvas moved to the output's pose (``output(y) = canvas(y − shift)``, flow(y − shift) − shift), filled where
    frame t stands in (``share``) by :func:`object_flow` over the box grown by ``_OBJECT_FILL_REACH`` (the fill reads
    the flow within a few σ of the object); float32 (h,w,C). Only that part of the frame is computed."""
    h, w = share.shape
    y0, y1, x0, x1 = box
    r = _OBJECT_FILL_REACH
    ry0, ry1, rx0, rx1 = max(0, y0 - r), min(h, y1 + r), max(0, x0 - r), min(w, x1 + r)
    dx, dy = shift
    sy0, sy1 = max(0, math.floor(ry0 - dy) - 2), min(h, math.ceil(ry1 - dy) + 2)
    sx0, sx1 = max(0, math.floor(rx0 - dx) - 2), min(w, math.ceil(rx1 - dx) + 2)
    src = cv2.multiply(np.ascontiguousarray(bwd_flow_px[sy0:sy1, sx0:sx1]), 1.0, dtype=cv2.CV_32F)
    m = np.array([[1.0, 0.0, rx0 - dx - sx0], [0.0, 1.0, ry0 - dy - sy0]])
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    flow = cv2.warpAffine(src, m, (rx1 - rx0, ry1 - ry0), flags=flags, borderMode=cv2.BORDER_REPLICATE)
    flow[..., 0] -= np.float32(dx)
    flow[..., 1] -= np.float32(dy)
    flow = object_flow(flow, share[ry0:ry1, rx0:rx1])[y0 - ry0 : y1 - ry0, x0 - rx0 : x1 - rx0]
    maps = flow + pixel_grid(flow.shape[:2])
    maps[..., 0] += np.float32(x0)
    maps[..., 1] += np.float32(y0)
    out = cv2.remap(raw, maps, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return image_of(out.reshape(flow.shape[:2] + raw.shape[2:]))


def object_average(
    base: np.ndarray, neighbours: list[np.ndarray], share: np.ndarray, offsets: list[int] | None = None
) -> np.ndarray:
    """Frame t's own pixels ``base`` (h,w,C) float32 around a moving object (where it stands in for the fusion,
    ``share`` > 0: the object keeps its own motion, which the fusion's registration does not follow) averaged with
    its neighbours' (each (h,w,C), unwarped as frame t is, at frame offsets ``offsets``): each aligned onto frame t by
    a dense flow (DIS) and weighted per pixel by how well it then agrees with frame t (exp(−(e/(k·s))²), e its
    box-averaged difference, s the median of e where ``share`` > 0.5, k ``_OBJECT_AGREE``), so that a neighbour the
    flow did not align (an occlusion, an object entering) falls out. With ``offsets`` the result is then moved to the
    frames' mean geometry: per pixel the flows f_j onto the neighbours are fitted by (j − t)·v + c (weighted least
    squares, frame t's own f = 0 with weight 1; v the object's motion, c the mean tilt less frame t's), and the
    average is read at x − c (c smoothed by a Gaussian of σ ``_OBJECT_CENTRE_SIGMA``). The single frame's noise and
    small-scale turbulent distortion average out (frame t unwarped by its true flow gains +0.9–1.2 dB inside the field
    clips' objects: docs/clips_field_oracles.md). Returns a new (h,w,C) float32 array."""
    base = np.ascontiguousarray(base, dtype=np.float32)
    base_gray = to_gray_u8(base)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    dis.setUseMeanNormalization(True)  # the frames' brightness flickers (scintillation, exposure)
    aligned, errors, flows = [], [], []
    for n in neighbours:
        n = np.ascontiguousarray(n)
        flow = dis.calc(base_gray, to_gray_u8(n), None)
        flows.append(flow)
        a = remap(n, flow)
        aligned.append(a)
        errors.append(cv2.blur(channel_mean(cv2.absdiff(a, base)), (_OBJECT_BOX, _OBJECT_BOX)))
    if not aligned:
        return base.copy()
    inside = share > 0.5
    pool = np.concatenate([e[inside] if inside.any() else e.ravel() for e in errors])
    scale = max(float(np.median(pool)), 1.0 / 255) * _OBJECT_AGREE
    total = base.copy()
    s0 = np.ones(base.shape[:2], np.float32)  # Σ w_j, frame t's weight 1 included
    s1, s2 = np.zeros_like(s0), np.zeros_like(s0)  # Σ w_j·d_j, Σ w_j·d_j²
    f0 = np.zeros(base.shape[:2] + (2,), np.float32)  # Σ w_j·f_j
    f1 = np.zeros_like(f0)  # Σ w_j·d_j·f_j
    for k, (a, e, f) in enumerate(zip(aligned, errors, flows)):
        wj = np.exp(-np.square(e / scale)).astype(np.float32)
        total += a * wj[..., None]
        s0 += wj
        if offsets is not None:
            d = np.float32(offsets[k])
            s1 += wj * d
            s2 += wj * d * d
            f0 += f * wj[..., None]
            f1 += f * (wj * d)[..., None]
    total /= s0[..., None]
    if offsets is None:
        return total
    det = s0 * s2 - s1 * s1
    ok = det > 1e-3  # the offsets spread: a line through them (else no correction)
    c = (s2[..., None] * f0 - s1[..., None] * f1) / np.where(ok, det, 1)[..., None]
    c[~ok] = 0
    c = cv2.GaussianBlur(c, (0, 0), _OBJECT_CENTRE_SIGMA)
    return remap(total, np.negative(c, out=c), consume=True)


def spread_share(variance: np.ndarray, mean: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Share of the single frame (H,W) = ``shape`` where the window's registered frames disagree more than
    registration can explain (``ClipState.spread``: their grey's temporal ``variance`` and ``mean``, at half size for
    ≥ 1 MP). A static scene's registered frames differ by noise and by what registration leaves, which shows on
    edges: a + b·|∇mean|², a the variance of the 30 % flattest pixels (median), b the median of (variance − a)/|∇|²
    over the 30 % steepest. The share rises from 0 where the box-averaged variance is ``_SPREAD_K`` times that (and
    at least ``_SPREAD_FLOOR``) to 1 at twice it, grown and softened as :func:`fallback_share`'s. A moving object, and
    the trail it leaves in the mean, makes the window's frames disagree whatever frame t shows there; frame t's own
    residual against the mean (:func:`fallback_share`) misses an object that stays in most of the window (field
    validation clips: 0.73-0.99 of the objects' boxes above 4× the median variance, against a share of 0.09-0.16 in
    :func:`fallback_share`'s three worst clips)."""
    half = variance.shape != tuple(shape)
    box = _FALLBACK_BOX // 2 + 1 if half else _FALLBACK_BOX
    v = cv2.blur(variance, (box, box))
    gx = cv2.Sobel(mean, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(mean, cv2.CV_32F, 0, 1, ksize=3)
    g2 = cv2.blur(cv2.addWeighted(gx * gx, 1 / 64, gy * gy, 1 / 64, 0), (box, box))  # |∇mean|², per px²
    vs, gs = v[::2, ::2].ravel(), g2[::2, ::2].ravel()
    flat_max, steep_min = np.quantile(gs, (0.3, 0.7))
    a = float(np.median(vs[gs <= flat_max]))
    steep = gs >= steep_min
    b = float(np.median(np.maximum(vs[steep] - a, 0) / np.maximum(gs[steep], 1e-12)))
    low = np.maximum(_SPREAD_K * (a + b * g2), _SPREAD_FLOOR)
    share = np.clip((v - low) / low, 0, 1).astype(np.float32)
    return _grown(share, box, tuple(shape), half)


def _grown(share: np.ndarray, box: int, shape: tuple[int, int], half: bool) -> np.ndarray:
    """A share grown by a disc (a square box printed square patches on real clips), then its edge softened by a box
    average as wide as the growth: it stays 1 over the object itself and fades over box/2 around it; at full size."""
    h, w = shape
    if not share.any():
        return np.zeros((h, w), np.float32) if half else share
    share = cv2.blur(cv2.dilate(share, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (box, box))), (box, box))
    return cv2.resize(share, (w, h), interpolation=cv2.INTER_LINEAR) if half else share


def fallback_share(warped: np.ndarray, fused: np.ndarray) -> np.ndarray:
    """Share of the single frame per pixel: 0 where the registered frame ``warped`` (as held: uint8, or float) agrees
    with the fusion within a few robust scales of its residual (box-averaged), rising to 1 where it stays far above (a
    moving object). On frames of ≥ 1 MP the box average is taken at half resolution (the box and the dilation span
    15 px: the decision is smooth at that scale) and the robust scale from every 4th residual."""
    r = channel_mean(cv2.absdiff(as_float(warped), fused))  # OpenCV: a quarter of numpy's time at 1080p
    h, w = r.shape
    half = is_large_frame(h, w)
    box = _FALLBACK_BOX // 2 + 1 if half else _FALLBACK_BOX
    if half:
        r = cv2.resize(r, ((w + 1) // 2, (h + 1) // 2), interpolation=cv2.INTER_AREA)
    r = cv2.blur(r, (box, box))
    scale = max(1.4826 * float(np.median(r[::2, ::2] if half else r)), 1e-3)
    z = (r / scale - _FALLBACK_LOW) / (_FALLBACK_HIGH - _FALLBACK_LOW)
    return _grown(np.clip(z, 0, 1).astype(np.float32), box, (h, w), half)
