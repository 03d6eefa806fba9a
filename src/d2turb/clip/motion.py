"""The image motion a clip's turbulence strength is measured from (``d2turb.clip.strength`` inverts it): the frames
registered to their temporal mean (phase correlation for the global shift, DIS for the dense flow), the mask of
pixels that register well enough (texture, residual, homogeneity), and the structure sums of the differential
displacement per separation and time lag; also the rough strength from a restoration's registered flows
(``registration_dr0``).
"""

from __future__ import annotations

from collections.abc import Iterable

import cv2
import numpy as np
import torch

from d2turb.clip.pipeline import ClipRestorer
from d2turb.clip.registration import DenseFlow, global_shift_px, to_hwc
from d2turb.defaults import NYQUIST_LAMBDA_OVER_D_PX
from d2turb.errors import D2TurbError
from d2turb.sim.params import MAX_DR0
from d2turb.sim.tilt import dr0_from_tilt_variance

MIN_FRAMES = 8  # fewer frames give too few time differences to fit the wind and the strength
MIN_VALID_FRACTION = 0.02  # of the analysed area; below it the clip is refused (below 0.15 it is widened)
TEXTURE_MIN = 1.0  # smallest eigenvalue of the 9×9 structure tensor of the reference, grey levels²/px²
# mean |frame(x + d) − ref| above RESIDUAL_REL times its median and above RESIDUAL_FLOOR grey levels excludes a pixel
# (moving objects, failed registration); the floor keeps the mask from following the tilt itself on clean clips
RESIDUAL_REL, RESIDUAL_FLOOR = 3.0, 8.0
# the tilt field is statistically homogeneous: a pixel whose temporal rms displacement (global part removed) exceeds
# HOMOGENEITY_MAX times the median is a registration failure (the true flow's 99th percentile is ~1.2× the median)
HOMOGENEITY_MAX = 1.6
RESIDUAL_REFUSE = 15.0  # median registration residual (grey levels) above which the frames are not one static scene
MARGIN_PX = 8
SEPARATIONS_PX = (16, 32, 64)  # below 16 px DIS keeps only about half of the differential power


# ---- frames → flows → statistics ------------------------------------------------------------------------------------
def gray_frames(frames) -> np.ndarray:
    """(T, H, W) float32 grey in [0, 255] from a list of (3,H,W) tensors / (H,W[,C]) arrays in [0, 1]."""
    out, shape = [], None
    for i, f in enumerate(frames):
        hwc = to_hwc(f)
        g = hwc[..., 0] if hwc.shape[2] == 1 else hwc[..., :3] @ np.array([0.299, 0.587, 0.114], np.float32)
        if shape is None:
            shape = g.shape
        elif g.shape != shape:
            raise D2TurbError(f"frame {i} is {g.shape[1]}x{g.shape[0]}, frame 0 is {shape[1]}x{shape[0]}")
        out.append(g * 255.0)
    if len(out) < MIN_FRAMES:
        raise D2TurbError(f"a clip needs at least {MIN_FRAMES} frames to measure turbulence, got {len(out)}")
    return np.stack(out).astype(np.float32)


def centre_crop(gray: np.ndarray, max_size: int) -> tuple[np.ndarray, list[int]]:
    _, h, w = gray.shape
    ch, cw = min(h, max_size), min(w, max_size)
    y0, x0 = (h - ch) // 2, (w - cw) // 2
    return gray[:, y0 : y0 + ch, x0 : x0 + cw], [x0, y0, cw, ch]


def structure_min_eigenvalue(gray: np.ndarray) -> np.ndarray:
    """Smallest eigenvalue (grey levels²/px²) of the structure tensor of a grey image (0–255) over 9×9 windows (DIS
    patches are 8 px): the texture a pixel gives the registration (``TEXTURE_MIN``)."""
    g = np.asarray(gray, np.float32)
    rx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8
    ry = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8
    sxx, syy, sxy = (cv2.boxFilter(a, -1, (9, 9)) for a in (rx * rx, ry * ry, rx * ry))
    return 0.5 * (sxx + syy) - np.sqrt(0.25 * (sxx - syy) ** 2 + sxy**2)


def register_clip(gray: np.ndarray, preset: str = "medium") -> tuple[np.ndarray, np.ndarray, dict]:
    """Flows (T, H, W, 2) of every frame onto the registered temporal mean, a validity mask (H, W) and diagnostics.

    The reference is the mean of the frames aligned by their global shift (phase correlation to frame 0, then to
    the first mean), so camera shake does not blur it; each frame's DIS flow starts from its global shift."""
    if float(gray.std(axis=0).max()) < 0.5 and float(gray.std()) < 0.5:
        raise D2TurbError("the frames are constant: nothing to register")
    u8 = [np.clip(g + 0.5, 0, 255).astype(np.uint8) for g in gray]
    h, w = gray.shape[1:]
    smallest = 2 * MARGIN_PX + 3 * SEPARATIONS_PX[0]  # the shortest separation fits three times inside the margins
    if min(h, w) < smallest:
        raise D2TurbError(f"frames of {w}x{h} are too small to measure turbulence (need {smallest} px)")
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))

    def aligned_mean(ref):
        shifts = [global_shift_px(ref, f) for f in u8]
        acc = np.zeros((h, w), np.float32)
        for g, (dx, dy) in zip(gray, shifts):
            acc += cv2.remap(g, gx + dx, gy + dy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return acc / len(gray), shifts

    ref, _ = aligned_mean(u8[0])
    ref_u8 = np.clip(ref + 0.5, 0, 255).astype(np.uint8)
    ref, shifts = aligned_mean(ref_u8)
    ref_u8 = np.clip(ref + 0.5, 0, 255).astype(np.uint8)
    dis = DenseFlow("medium" if preset is None else preset)
    flows = np.empty((len(gray), h, w, 2), np.float32)
    residual = np.zeros((h, w), np.float32)
    fused = np.zeros((h, w), np.float32)  # the registered frames' mean: its blur is the short-exposure blur
    for i, (f, (dx, dy)) in enumerate(zip(u8, shifts)):
        init = np.empty((h, w, 2), np.float32)
        init[..., 0], init[..., 1] = dx, dy
        flows[i] = dis(ref_u8, f, init)
        warped = cv2.remap(gray[i], gx + flows[i, ..., 0], gy + flows[i, ..., 1], cv2.INTER_LINEAR)
        residual += np.abs(warped - ref)
        fused += warped
    residual /= len(gray)
    lam_min = structure_min_eigenvalue(ref)
    inner_res = residual[MARGIN_PX:-MARGIN_PX, MARGIN_PX:-MARGIN_PX]
    mask = (lam_min > TEXTURE_MIN) & (residual < max(RESIDUAL_REL * float(np.median(inner_res)), RESIDUAL_FLOOR))
    mask[:MARGIN_PX], mask[-MARGIN_PX:], mask[:, :MARGIN_PX], mask[:, -MARGIN_PX:] = False, False, False, False
    if mask.any():
        local = flows - np.median(flows[:, mask], axis=1)[:, None, None, :]
        rms = np.sqrt(local.var(axis=0).mean(-1))
        mask &= rms < HOMOGENEITY_MAX * max(float(np.median(rms[mask])), 1e-3)
    inner = (h - 2 * MARGIN_PX) * (w - 2 * MARGIN_PX)
    diag = {
        "valid_fraction": float(mask.sum() / inner),
        "textured_fraction": float((lam_min > TEXTURE_MIN)[MARGIN_PX:-MARGIN_PX, MARGIN_PX:-MARGIN_PX].mean()),
        "median_residual_grey": float(np.median(residual[MARGIN_PX:-MARGIN_PX, MARGIN_PX:-MARGIN_PX])),
        "global_shift_rms_px": float(np.sqrt(np.mean(np.var(np.array(shifts), axis=0).sum()))),
        "_fused": fused / len(gray),
    }
    return flows, mask, diag


def register_measurable(gray: np.ndarray, preset: str = "medium") -> tuple[np.ndarray, np.ndarray, dict]:
    """:func:`register_clip` with the refusals of :func:`measure_clip` (frames that are not one static scene, too
    little usable area) as one-line ``D2TurbError``."""
    flows, mask, diag = register_clip(gray, preset)
    if diag["textured_fraction"] < MIN_VALID_FRACTION:  # first: without texture the residual means nothing
        raise D2TurbError(
            f"cannot measure this clip: only {100 * diag['textured_fraction']:.1f} % of the analysed area has texture "
            f"(need {100 * MIN_VALID_FRACTION:.0f} %): a flat scene (sky, a plain wall) shows no motion to measure"
        )
    if diag["median_residual_grey"] > RESIDUAL_REFUSE:
        raise D2TurbError(
            f"cannot measure this clip: the frames do not register onto one static scene (median residual "
            f"{diag['median_residual_grey']:.1f} grey levels, limit {RESIDUAL_REFUSE:g}): a moving camera or scene, a "
            "cut, or frames of different scenes"
        )
    if diag["valid_fraction"] < MIN_VALID_FRACTION:
        raise D2TurbError(
            f"cannot measure this clip: only {100 * diag['valid_fraction']:.1f} % of the analysed area has the texture "
            f"and registration quality needed (need {100 * MIN_VALID_FRACTION:.0f} %; textured "
            f"{100 * diag['textured_fraction']:.0f} %, median registration residual {diag['median_residual_grey']:.1f} "
            "grey levels)"
        )
    return flows, mask, diag


def separations_for(h: int, w: int) -> list[int]:
    usable = min(h, w) - 2 * MARGIN_PX
    return [r for r in SEPARATIONS_PX if r <= usable // 3]


def lag_sums(flows: np.ndarray, mask: np.ndarray, seps, tiles: int = 4, stride: int = 2):
    """Σ over time of (u(t+τ) − u(t))² for the differential displacement of every series j = (separation,
    orientation x/y, component x/y), summed per spatial tile of the first point of each pair.

    Returns (num (tiles², J, T), pairs (tiles², J), series [(r, orientation, component)]); num[..., 0] is unused."""
    t_len, h, w, _ = flows.shape
    ys, xs = np.arange(0, h, stride), np.arange(0, w, stride)
    series, nums, counts = [], [], []
    n_tiles = tiles * tiles
    for r in seps:
        for orient in (0, 1):  # separation along x, along y
            dy, dx = (0, r) if orient == 0 else (r, 0)
            yy, xx = np.meshgrid(ys[ys + dy < h], xs[xs + dx < w], indexing="ij")
            ok = mask[yy, xx] & mask[yy + dy, xx + dx]
            y1, x1 = yy[ok], xx[ok]
            tile = np.minimum(y1 * tiles // h, tiles - 1) * tiles + np.minimum(x1 * tiles // w, tiles - 1)
            for comp in (0, 1):
                u = flows[:, y1, x1, comp] - flows[:, y1 + dy, x1 + dx, comp]  # (T, P): global motion cancels
                u = u - u.mean(0)
                sq = np.cumsum(u * u, axis=0)
                spec = np.fft.rfft(u, n=2 * t_len, axis=0)
                acf = np.fft.irfft(spec * np.conj(spec), n=2 * t_len, axis=0)[:t_len]  # Σ_t u_t u_{t+τ}
                total = sq[-1]
                lags = np.arange(t_len)
                head = total[None] - np.concatenate([np.zeros((1, u.shape[1])), sq[:-1]])  # Σ_{t≥τ} u²
                tail = sq[::-1]  # Σ_{t<T−τ} u² at index τ
                per = head[lags] + tail[lags] - 2 * acf  # (T, P)
                num = np.zeros((n_tiles, t_len))
                for k in range(t_len):
                    num[:, k] = np.bincount(tile, weights=per[k], minlength=n_tiles)
                nums.append(num)
                counts.append(np.bincount(tile, minlength=n_tiles).astype(np.float64))
                series.append((r, orient, comp))
    return np.stack(nums, 1), np.stack(counts, 1), series


# Share of the tilt variance (Z-tilt per axis, docs/physics.md §2) that the registered flows of a window of
# REGISTRATION_WINDOW frames carry (each frame's mean shift removed): the registration sees only the part that
# changes within the window, and DIS smooths it. Median over the 24 validation clips (docs/clips.md).
OBSERVED_TILT_SHARE = 0.13
REGISTRATION_WINDOW = 32


def flow_variance_px2(bwd_flow_px: torch.Tensor) -> float:
    """Per-axis variance (px²) of one (2, H, W) flow about its own mean (the frame's global shift, camera shake)."""
    f = bwd_flow_px.double()
    return float(((f - f.mean((1, 2), keepdim=True)) ** 2).mean()) / 2


def registration_tilt_variance(frames: Iterable, temporal: int = REGISTRATION_WINDOW, preset: str = "fast") -> float:
    """Per-axis variance (px²) of the backward flows that register each frame of ``frames`` onto its window's
    fusion (:class:`ClipRestorer`, no deblur), each frame's mean shift (camera shake) removed, averaged over the
    frames."""
    total, count = 0.0, 0
    for out in ClipRestorer(temporal=temporal, preset=preset, fallback=False).restore(frames):
        total += flow_variance_px2(out.bwd_flow_px)
        count += 1
    return total / max(count, 1)


def registration_dr0(
    frames: Iterable, lambda_over_d_px: float = NYQUIST_LAMBDA_OVER_D_PX, preset: str = "fast"
) -> float:
    """D/r0 from the clip's own registration, for a clip that ``d2turb measure`` cannot measure: the tilt variance
    is the registered flows' variance over ``OBSERVED_TILT_SHARE`` (calibrated on the simulated validation clips at a
    window of ``REGISTRATION_WINDOW`` frames; a rough estimate: 0.10–0.15 there, unknown on real footage), inverted by
    the Z-tilt law σ² = 0.1816 (λ/D)² (D/r0)^(5/3) with λ/D in pixels. Clipped to [0.05, MAX_DR0]."""
    var = registration_tilt_variance(frames, REGISTRATION_WINDOW, preset) / OBSERVED_TILT_SHARE
    dr0 = float(dr0_from_tilt_variance(var, lambda_over_d_px))
    return min(max(dr0, 0.05), MAX_DR0)


__all__ = [
    "gray_frames",
    "centre_crop",
    "structure_min_eigenvalue",
    "register_clip",
    "register_measurable",
    "separations_for",
    "lag_sums",
    "flow_variance_px2",
    "registration_tilt_variance",
    "registration_dr0",
]
