"""Turbulence strength from a clip of a static scene: D/r0, r0, Cn² and the isoplanatic angle θ0, with a 90 %
interval (docs/measure.md).

Method. Each frame is registered to the temporal mean (``d2turb.clip.registration``: phase correlation for the global
shift, DIS for the dense flow). For pairs of image points r apart (several separations, along x and y) the
*differential* displacement u(t) = d(x, t) − d(x + r, t) is formed, in which any global motion (camera shake,
pointing drift) cancels exactly. Its temporal structure function D̂(τ) = ⟨(u(t+τ) − u(t))²⟩ is free of the
unknown per-pixel mean (the clip-level mean tilt that a finite window cannot see cancels in a time difference);
its expectation under Kolmogorov theory with frozen flow and boiling is

    E D̂_j(τ) = 2 ε_j σ² [G_j(0) − G_j(τ)],   σ² = 0.1816 (λ/(D·ifov))² (D/r0)^(5/3) px²,

with G the path-integrated differential-tilt covariance of ``d2turb.sim.tilt.differential_tilt_covariance``
(I0 ± I2 layer correlations, (1 − z/L)^(5/3) weights) and ε_j the registration's loss of differential-tilt power
at separation j, measured on simulated calibration clips as a function of the separation, the strength and the
tilt's correlation scale D/(ifov·L) (``GAIN_TABLE``). The wind (speed per frame, direction) and the boiling are
nuisance parameters fitted on a grid by the shape of D̂(τ) against τ; σ² is then a ratio of sums. The 90 %
interval is log-normal: the spread of a bootstrap over spatial tiles (the fit redone per resample) and the
clip-to-clip scatter measured on the calibration clips (``CLIP_LOG_SD``: the registration gain's dependence on
the scene, the turbulence at scales larger than a tile; larger for windows shorter than 64 frames), in quadrature.

Unknown optics (issue 36): λ/(D·ifov) without ifov_rad and the correlation scale without path_length_m are
marginalised over the prior grids ``Q_GRID`` × ``FOOTPRINT_PX_GRID`` (λ/(D·ifov) narrowed by the fused frame's blur,
``BLUR_GAIN``); the interval is the union of the grid's intervals, a given parameter's interval is intersected with
it. A correlation scale below the calibrated 4 px and little texture widen the interval (uncalibrated terms), a tilt
rms above the calibrated 3 px its lower bound (calibrated: there the registration errs high, ``LARGE_TILT_LOG_SD``); a
90 % interval wider than ``MAX_SPAN`` is refused naming the term that widens it most.
"""

from __future__ import annotations

import math

import numpy as np

from d2turb.clip.motion import (  # the observable; its names stay importable from here (benchmarks, tests)
    MIN_FRAMES,
    centre_crop,
    flow_variance_px2,
    gray_frames,
    lag_sums,
    register_clip,
    register_measurable,
    registration_dr0,
    registration_tilt_variance,
    separations_for,
)
from d2turb.errors import D2TurbError
from d2turb.sim.otf import short_exposure_width
from d2turb.sim.params import Optics, as_optics, r0_cn2_theta0
from d2turb.sim.tilt import differential_tilt_covariance, dr0_from_tilt_variance, tilt_variance_px2

# registration gain ε(r, D/r0, footprint): DIS-measured / true differential-tilt power at separation r px, from
# simulated calibration clips (crops of train-split images, never the validation images: bsds500, outdoor views of
# camvid, strecha_mvs, sfm_landmarks, the 32 least textured train crops, and every "field" geometry at D/r0 3.5 and
# 4.5; 256², 64 frames, wind 1–3 m/s, the default optics and the "field" bank; docs/measure.md,
# benchmarks/measure/fitgain.py): a smooth least-squares model of ln ε in ln r, ln footprint and D/r0 tabulated here.
# Index [footprint][D/r0][separation]; linear in ln footprint, D/r0 and ln r between the nodes, clamped outside (a
# footprint below the first node is refused by measure_clip). The footprint is the tilt's correlation scale
# D/(ifov·L) in px (38 px for the default optics).
GAIN_FOOTPRINT_PX = (4.0, 8.0, 16.0, 38.1)
GAIN_DR0 = (1.5, 2.5, 3.5, 4.5)
GAIN_SEPARATIONS_PX = (16, 32, 64)
GAIN_TABLE = (
    ((0.468, 0.591, 0.700), (0.472, 0.583, 0.676), (0.476, 0.576, 0.653), (0.480, 0.568, 0.631)),
    ((0.558, 0.683, 0.785), (0.572, 0.685, 0.770), (0.586, 0.687, 0.756), (0.600, 0.688, 0.741)),
    ((0.646, 0.766, 0.853), (0.672, 0.780, 0.850), (0.699, 0.795, 0.847), (0.727, 0.809, 0.844)),
    ((0.743, 0.848, 0.907), (0.788, 0.880, 0.922), (0.836, 0.914, 0.937), (0.887, 0.949, 0.952)),
)
# the interval: ln D̂ ± z·sqrt(s_tiles² + s_clip²), s_tiles the sd of ln D̂ over the tile bootstrap and s_clip the
# clip-to-clip scatter of ln(D̂/D) that the tiles do not see: the registration gain varies with the scene's texture,
# and the tiles of one clip share its turbulence at scales larger than a tile. s_clip from the calibration clips,
# the gain model refitted without each clip: per clip ln(D̂/D)² minus its bootstrap variance, least squares against
# D/r0 (the scatter grows with the strength); per D/r0 of GAIN_DR0, linear between, clamped outside
# (benchmarks/measure/fitgain.py; 156 accepted calibration clips, 31 of them outdoor scenes, 18 low-texture crops)
CLIP_LOG_SD = (0.037, 0.041, 0.044, 0.047)
# a shorter window samples less of the turbulence: the clip term's variance grows by CLIP_WINDOW_VAR·(64/T − 1),
# fitted on the calibration clips' windows of 16 and 32 frames with their 64-frame estimates (fitgain.py)
CLIP_FRAMES = 64
CLIP_WINDOW_VAR = 0.00061
# two-sided 90 %: the Student-t quantile t_0.95 with the degrees of freedom of the clip term's fit (156 clips, two
# coefficients: 154), since s_clip is estimated from a finite number of clips; the normal Φ⁻¹(0.95) = 1.6449 is its
# limit
CLIP_DOF = 154
Z90 = 1.6548083854766773  # scipy.stats.t.ppf(0.95, 154)
WIND_GRID = np.geomspace(0.003, 3.0, 13)  # v/(fps·D): the wind's shift per frame in aperture diameters
DIR_GRID = (0.0, 45.0, 90.0, 135.0)
BOIL_GRID = (0.0, 0.03, 0.1, 0.3)
# ---- what the user did not give: prior ranges, marginalised (docs/measure.md, "Unknown optics") ----
# λ/(D·ifov), the diffraction angle in px (2 at Nyquist): without ifov_rad, the prior range (a resized video, an
# unknown lens), narrowed by the blind estimate from the clip's blur (BLUR_EXCESS_MAX) where that is confident
Q_PRIOR = (0.7, 6.0)
Q_GRID = np.geomspace(*Q_PRIOR, 13)
# the tilt's correlation scale D/(ifov·L) in px: without path_length_m the range of a path of 0.3–20 km at the default
# aperture and wavelength and Nyquist sampling (1.9–127 px); with it, D²·q/(λ·L) clamped to this range
FOOTPRINT_PRIOR_PX = (2.0, 128.0)
FOOTPRINT_PX_GRID = np.geomspace(*FOOTPRINT_PRIOR_PX, 13)
# blind λ/(D·ifov): the fused (registered, averaged) frame's blur σ_b (restore.blur.estimate_blur) against the
# optical short-exposure blur q·s(D/r0) (s: the Gaussian-equivalent width of the tilt-removed OTF of sim.otf in units
# of λ/D, :func:`short_exposure_width`). On simulated clips (the oracle: the simulator's known q and D/r0; q 2–3, D/r0
# 2–4, docs/measure.md) σ_b = c·q·s(D/r0) with c 0.48–0.57; BLUR_GAIN is that range widened. Real clips add blur the
# optics model leaves out (lens, sensor, codec): σ_b up to BLUR_EXCESS_MAX times the optical part. A grid point
# (q, D/r0) is kept when [c_lo·q·s, c_hi·q·s·BLUR_EXCESS_MAX] meets the blur's 90 % interval. Tilt and blur both grow
# like λ/r0 when D/r0 is large (T/σ² = 0.1816 (D/r0)^(5/3)/s² varies by 25 % over D/r0 1.5–8), so the blur fixes q
# for a given D/r0 rather than D/r0 itself: it narrows the prior, it does not replace the optics.
BLUR_GAIN = (0.42, 0.65)
BLUR_EXCESS_MAX = 1.5
# below the calibrated footprints (GAIN_FOOTPRINT_PX[0]) the gain is clamped: an extra log-sd of
# EXTRAPOLATION_LOG_SD per unit of ln(4 px / footprint) (uncalibrated widening instead of a refusal)
EXTRAPOLATION_LOG_SD = 0.3
# beyond the gain table's box at its strong end, calibrated (benchmarks/measure/cal36.py, fit36.py: 81 clips of the
# train folder bsds500 drawn in issue 36's ranges, the optics given): above the box's largest tilt rms (D/r0 4.5 at
# λ/(D·ifov) = 2 px: 2.98 px) DIS's mismatches ADD variance, so the estimate errs high (25 of the 28 calibration
# clips there, ln(estimate/truth) up to +1.8; the other three within 8 % low); the interval's LOWER bound is widened
# by an extra log-sd LARGE_TILT_LOG_SD per unit of ln(tilt rms / 2.98 px), the rms of the log errors' excess over the
# interval's own (non-negative least squares; coverage of those clips 0.43 → 0.96). A footprint above the largest
# node (38 px) needed no term of its own in that fit.
CALIBRATED_TILT_RMS_PX = math.sqrt(float(tilt_variance_px2(GAIN_DR0[-1], 1.0, 2.0, 1.0)))
LARGE_TILT_LOG_SD = 0.96
# little usable area: an extra log-sd LOW_TEXTURE_LOG_SD·sqrt(TEXTURED_FULL/valid − 1) below TEXTURED_FULL
# (uncalibrated widening; the tile bootstrap already widens with fewer pairs)
TEXTURED_FULL = 0.15
LOW_TEXTURE_LOG_SD = 0.1
MAX_SPAN = 3.0  # the 90 % interval's hi/lo above which the clip is refused, naming the parameter that widens it
NEGLIGIBLE_DR0 = 0.3  # ... unless its upper bound is below this: "no measurable turbulence" is an answer


def footprint_grid(optics: Optics) -> list[float]:
    """ifov·L/D of the footprint prior grid (the tilt's correlation scale D/(ifov·L) = 1/value, in px)."""
    return list(1.0 / FOOTPRINT_PX_GRID)


def _short_widths(dr0: np.ndarray) -> np.ndarray:
    nodes = np.geomspace(0.05, 20.0, 40)
    table = np.array([short_exposure_width(x) for x in nodes])
    return np.interp(np.clip(dr0, nodes[0], nodes[-1]), nodes, table)


def registration_gain(sep_px, dr0: float, footprint_px: float = 38.1) -> np.ndarray:
    """ε for separations ``sep_px`` at strength ``dr0`` and tilt correlation scale ``footprint_px`` = D/(ifov·L)
    from ``GAIN_TABLE`` (linear in ln footprint, D/r0 and ln r; clamped outside the table)."""
    table = np.asarray(GAIN_TABLE)  # (F, X, R)
    lf = np.clip(math.log(footprint_px), math.log(GAIN_FOOTPRINT_PX[0]), math.log(GAIN_FOOTPRINT_PX[-1]))
    at_f = np.array(
        [
            [np.interp(lf, np.log(GAIN_FOOTPRINT_PX), table[:, i, k]) for k in range(table.shape[2])]
            for i in range(table.shape[1])
        ]
    )  # (X, R)
    at_dr0 = np.array([np.interp(dr0, GAIN_DR0, at_f[:, k]) for k in range(at_f.shape[1])])
    return np.interp(np.log(np.asarray(sep_px, np.float64)), np.log(GAIN_SEPARATIONS_PX), at_dr0)


def clip_log_sd(dr0: float, frames: int = CLIP_FRAMES) -> float:
    """The interval's clip-to-clip term (sd of ln D/r0) at strength ``dr0`` from ``CLIP_LOG_SD``, for a clip or window
    of ``frames`` frames: variance CLIP_LOG_SD² + CLIP_WINDOW_VAR·(CLIP_FRAMES/frames − 1), not below its value at
    CLIP_FRAMES (longer clips keep the calibrated term)."""
    var = float(np.interp(dr0, GAIN_DR0, CLIP_LOG_SD)) ** 2
    return math.sqrt(var + CLIP_WINDOW_VAR * max(CLIP_FRAMES / int(frames) - 1.0, 0.0))


def log_normal_interval(estimate: float, log_sds, z: float = Z90) -> tuple[float, float]:
    """``estimate``·exp(∓z·s) with s the quadrature sum of the independent log-sds ``log_sds`` (a 90 % interval
    with the default z, the t quantile of the calibrated clip term, when ln of the estimate is normal about ln of
    the truth)."""
    s = math.sqrt(sum(float(v) ** 2 for v in log_sds))
    return estimate * math.exp(-z * s), estimate * math.exp(z * s)


# ---- the fit ----------------------------------------------------------------------------------------------------
def _models(series, t_len: int, footprints, geometry="path"):
    """Unit structure-function models 2[G(0) − G(τ)] (F, V, Dir, B, J, T) on the nuisance grid."""
    seps = sorted({r for r, _, _ in series})
    lags = np.arange(t_len)
    out = np.zeros((len(footprints), len(WIND_GRID), len(DIR_GRID), len(BOIL_GRID), len(series), t_len))
    boil_f = np.array([(1 - b) ** (lags / 2) for b in BOIL_GRID])  # (B, T)
    for fi, a in enumerate(footprints):
        for vi, v in enumerate(WIND_GRID):
            for di, d in enumerate(DIR_GRID):
                vec = [[r, 0] for r in seps] + [[0, r] for r in seps]
                g = differential_tilt_covariance(vec, lags, a, v, d, 0.0, geometry)  # (2S, 2, T)
                for j, (r, orient, comp) in enumerate(series):
                    gj = g[seps.index(r) + orient * len(seps), comp]
                    out[fi, vi, di, :, j] = 2 * (gj[0] - gj[None] * boil_f)
    return out


def _fit(num, pairs, t_len, models, gains):
    """(σ², index of the best nuisance point) from summed num (J, T) and pairs (J,); ``gains`` (F, J): the
    registration gain per footprint of the grid and series."""
    lags = np.arange(t_len)
    w = pairs[:, None] * (t_len - lags)[None]  # pair-lags per (j, τ)
    w[:, 0] = 0
    with np.errstate(invalid="ignore", divide="ignore"):
        data = np.where(w > 0, num / np.maximum(w, 1), 0.0)  # D̂_j(τ)
    m = models * np.asarray(gains, np.float64)[:, None, None, None, :, None]
    sig2 = (w * data).sum((-1, -2)) / np.maximum((w * m).sum((-1, -2)), 1e-300)  # ratio of sums per grid point
    fit = sig2[..., None, None] * m
    resid = (w * (data - fit) ** 2 / np.maximum(fit, 1e-12) ** 2).sum((-1, -2))
    best = np.unravel_index(np.argmin(resid), resid.shape)
    return float(sig2[best]), best


def measure_clip(
    frames,
    optics: Optics | dict | None = None,
    window: int | None = None,
    bootstrap: int = 200,
    max_size: int = 320,
    seed: int = 0,
    preset: str = "medium",
    extrapolate: bool = False,
    blind: bool = True,
    seeing_answers: bool = False,
) -> dict:
    """Measure D/r0 (and r0, Cn², θ0 with a path length) from the frames of a static scene.

    Every pixel-level parameter the optics do not give is marginalised over its prior range (``Q_PRIOR`` for
    λ/(D·ifov) without ifov_rad, narrowed by the blind estimate from the clip's blur; ``FOOTPRINT_PRIOR_PX`` for the
    tilt's correlation scale without path_length_m): the 90 % interval is the union of the intervals over the prior
    grid, so that giving a parameter can only narrow it (the given interval is intersected with it, which moves its
    bounds by at most the grid's interpolation). ``result["parameters"]`` says which were given and which were
    marginalised, with their ranges.

    Args:
        frames: a sequence of (3,H,W) tensors or (H,W[,C]) arrays in [0, 1], one per frame.
        optics: :class:`Optics`, a dict of its fields (aperture_m, wavelength_m, ifov_rad, path_length_m, fps) or
            a ``TurbulenceParams`` (its D/r0 is ignored; its ifov and path count as given).
        window: frames per window for a series of estimates over time (None: the whole clip only).
        bootstrap: resamples for the 90 % interval. max_size: the centre crop analysed (px per side).
        extrapolate: give a number even when the 90 % interval spans more than ``MAX_SPAN`` (a rough strength).
        blind: narrow λ/(D·ifov) by the blur of the fused frame when ifov_rad is not given.
        seeing_answers: without ifov_rad, a D/r0 interval wider than ``MAX_SPAN`` is not refused when the seeing
            angle's (``seeing_px``) is within it: that is the answer, and ``dr0_determined`` is False (``measure``).

    Returns:
        A dict: ``dr0``, its 90 % interval ``dr0_ci``, ``dr0_determined`` (its interval within ``MAX_SPAN``),
        ``seeing_px`` = λ/(r0·ifov) (the seeing angle in px) and its ``seeing_px_ci``, ``r0_m``, ``cn2`` and
        ``theta0_urad`` (None without a path length), ``parameters`` (given, marginalised), ``widened_by``,
        ``windows``, ``inputs``, the diagnostics.
    Shape:
        - frames: N ≥ 8 (``MIN_FRAMES``) frames of :math:`(3, H, W)`, :math:`(H, W)` or :math:`(H, W, C)`.
    Raises:
        D2TurbError: input that cannot be measured, or an interval wider than ``MAX_SPAN`` without ``extrapolate``.
    """
    optics = as_optics(optics)
    gray = gray_frames(frames)
    if window is not None and (int(window) < MIN_FRAMES or int(window) > len(gray)):
        raise D2TurbError(f"window must be between {MIN_FRAMES} and the {len(gray)} frames of the clip, got {window}")
    gray, crop = centre_crop(gray, max_size)
    flows, mask, diag = register_measurable(gray, preset)
    fused = diag.pop("_fused")
    h, w = mask.shape
    seps = separations_for(h, w)
    blur = None
    if blind and not optics.ifov_known:
        from d2turb.clip.blur import estimate_blur  # restore.files imports this module: at the top, a cycle

        if min(fused.shape) >= 32:
            est = estimate_blur(np.clip(fused / 255.0, 0, 1).astype(np.float32))
            blur = {"sigma_px": est.sigma_px, "sigma_ci": list(est.sigma_ci), "confident": est.confident}
            if not est.confident:
                blur["reason"] = est.reason
    extra = {"texture": _texture_log_sd(diag["valid_fraction"])}
    result = estimate_from_sums(*lag_sums(flows, mask, seps), optics, None, bootstrap, seed, {}, blur, extra)
    result.update(diag)
    lo, hi = result["dr0_ci"]
    s_lo, s_hi = result["seeing_px_ci"]
    wide = not lo > 0 or hi / lo > MAX_SPAN
    result["dr0_determined"] = not wide
    seeing_only = seeing_answers and not optics.ifov_known and s_lo > 0 and s_hi / s_lo <= MAX_SPAN
    if not extrapolate and wide and not seeing_only:
        span = hi / lo if lo > 0 else math.inf
        seeing = (
            f"; the seeing angle λ/(r0·ifov) is {result['seeing_px']:.2f} px [{s_lo:.2f}, {s_hi:.2f}]"
            if not optics.ifov_known
            else ""
        )
        raise D2TurbError(
            f"cannot measure this clip: the 90 % interval of D/r0 [{lo:.2f}, {hi:.2f}] spans {span:.1f}x (limit "
            f"{MAX_SPAN:g}x), widened most by {result['widened_by']}{seeing}"
        )
    if window:
        series = []
        models: dict = {}
        for s in range(0, len(gray) - int(window) + 1, int(window)):
            est = estimate_from_sums(
                *lag_sums(flows[s : s + int(window)], mask, seps), optics, None, bootstrap, seed, models, blur, extra
            )
            keys = ("dr0", "dr0_ci", "seeing_px", "seeing_px_ci")
            series.append({"start_frame": s, "frames": int(window), **{k: est[k] for k in keys}})
        result["windows"] = series
    result["inputs"] = {
        "frames": len(gray),
        "crop_xywh": crop,
        "separations_px": seps,
        "aperture_m": optics.aperture_m,
        "wavelength_m": optics.wavelength_m,
        "ifov_rad": optics.ifov_rad if optics.ifov_known else None,
        "path_length_m": optics.path_length_m,
        "fps": optics.fps,
        "window": window,
        "registration": f"DIS {preset}",
    }
    return result


def _texture_log_sd(valid_fraction: float) -> float:
    if valid_fraction >= TEXTURED_FULL:
        return 0.0
    return LOW_TEXTURE_LOG_SD * math.sqrt(TEXTURED_FULL / max(valid_fraction, 1e-6) - 1.0)


def _fit_per_footprint(num, pairs, t_len, models, gains):
    """σ² (F,) and the weighted residual (F,) at the best nuisance point (wind, direction, boiling) of each footprint
    of ``models`` (F, V, Dir, B, J, T); ``gains`` (F, J)."""
    lags = np.arange(t_len)
    w = pairs[:, None] * (t_len - lags)[None]
    w[:, 0] = 0
    with np.errstate(invalid="ignore", divide="ignore"):
        data = np.where(w > 0, num / np.maximum(w, 1), 0.0)
    m = models * np.asarray(gains, np.float64)[:, None, None, None, :, None]
    sig2 = (w * data).sum((-1, -2)) / np.maximum((w * m).sum((-1, -2)), 1e-300)  # (F, V, Dir, B)
    fit = sig2[..., None, None] * m
    resid = (w * (data - fit) ** 2 / np.maximum(fit, 1e-12) ** 2).sum((-1, -2))
    flat = resid.reshape(len(resid), -1)
    best = flat.argmin(1)
    return sig2.reshape(len(sig2), -1)[np.arange(len(sig2)), best], flat[np.arange(len(flat)), best], best


def _points(optics: Optics):
    """The (footprint px, q) grid of the parameters not given and the exact points of the given ones:
    (grid_f (F,), grid_q (Q,), given [(f, q)] or None)."""
    q_given = optics.wavelength_m / (optics.aperture_m * optics.ifov_rad) if optics.ifov_known else None
    grid_q = Q_GRID if q_given is None else np.array([q_given])
    grid_f = np.array(FOOTPRINT_PX_GRID)
    if optics.path_length_m is None:
        return grid_f, grid_q, None
    f_of_q = np.clip(optics.aperture_m**2 * grid_q / (optics.wavelength_m * optics.path_length_m), *FOOTPRINT_PRIOR_PX)
    return grid_f, grid_q, f_of_q


def estimate_from_sums(
    num, pairs, series, optics: Optics, footprints=None, bootstrap=200, seed=0, cache=None, blur=None, extra=None
) -> dict:
    """The fit and the interval from the structure sums of :func:`lag_sums` (what :func:`measure_clip` does after
    the registration). ``footprints`` is ignored (kept for old callers: the grid is ``FOOTPRINT_PX_GRID``); ``blur``:
    the fused frame's blur estimate for the blind λ/(D·ifov); ``extra``: named extra log-sds of the interval."""
    optics = as_optics(optics)
    cache = {} if cache is None else cache
    extra = dict(extra or {})
    t_len = num.shape[-1]
    grid_f, grid_q, f_given = _points(optics)
    fs = np.concatenate([grid_f, f_given]) if f_given is not None else grid_f
    key = (t_len, tuple(np.round(fs, 9)))
    if key not in cache:
        cache[key] = _models(series, t_len, list(1.0 / fs))
    models = cache[key]
    seps = [r for r, _, _ in series]
    n_f, n_q = len(fs), len(grid_q)
    dr0 = np.full((n_f, n_q), 2.5)
    tot_num, tot_pairs = num.sum(0), pairs.sum(0)
    for qi, q in enumerate(grid_q):  # the gain depends on the strength: a fixed point per (footprint, q)
        for _ in range(3):
            gains = np.stack([registration_gain(seps, dr0[fi, qi], fs[fi]) for fi in range(n_f)])
            sig2, resid, best = _fit_per_footprint(tot_num, tot_pairs, t_len, models, gains)
            dr0[:, qi] = dr0_from_tilt_variance(np.maximum(sig2, 0.0), 1.0, float(q), 1.0)
    # tile bootstrap per footprint at the gains of the central q (ln D/r0 = 3/5 ln σ² + const: its sd does not depend
    # on q)
    qc = int(np.argmin(np.abs(np.log(grid_q / 2.0))))
    gains = np.stack([registration_gain(seps, dr0[fi, qc], fs[fi]) for fi in range(n_f)])
    rng = np.random.default_rng(seed)
    n_tiles = num.shape[0]
    boot = []
    for _ in range(bootstrap):
        pick = rng.integers(0, n_tiles, n_tiles)
        boot.append(_fit_per_footprint(num[pick].sum(0), pairs[pick].sum(0), t_len, models, gains)[0])
    with np.errstate(divide="ignore", invalid="ignore"):
        tiles_sd = np.std(0.6 * np.log(np.array(boot)), axis=0) if boot else np.zeros(n_f)
    tiles_sd = np.where(np.isfinite(tiles_sd), tiles_sd, 0.0)
    ext_sd = EXTRAPOLATION_LOG_SD * np.log(np.maximum(GAIN_FOOTPRINT_PX[0] / fs, 1.0))
    tilt_rms = np.sqrt(tilt_variance_px2(dr0, 1.0, grid_q[None, :], 1.0))  # per node: λ/(D·ifov) = q px
    tilt_sd = LARGE_TILT_LOG_SD * np.log(np.maximum(tilt_rms / CALIBRATED_TILT_RMS_PX, 1.0))
    clip_sd = np.vectorize(lambda x: clip_log_sd(x, t_len))(dr0)
    other = sum(v * v for v in extra.values())
    total_sd = np.sqrt(tiles_sd[:, None] ** 2 + ext_sd[:, None] ** 2 + clip_sd**2 + other)
    lo, hi = dr0 * np.exp(-Z90 * np.sqrt(total_sd**2 + tilt_sd**2)), dr0 * np.exp(Z90 * total_sd)
    # the blind λ/(D·ifov): keep the grid points whose optical blur q·s(D/r0) the fused frame's blur allows
    allowed = np.ones((n_f, n_q), bool)
    blur_used = False
    if blur is not None and blur.get("confident") and blur["sigma_ci"][1] > 0:
        optical = grid_q[None, :] * _short_widths(dr0)
        ok = (BLUR_GAIN[0] * optical <= blur["sigma_ci"][1]) & (
            BLUR_GAIN[1] * BLUR_EXCESS_MAX * optical >= blur["sigma_ci"][0]
        )
        if ok[: len(grid_f)].any():
            allowed, blur_used = ok, True
    # the best footprint by the fit; the point estimate at it and at the central allowed q
    _, resid, best = _fit_per_footprint(tot_num, tot_pairs, t_len, models, gains)
    if f_given is None:
        cand = [fi for fi in range(len(grid_f)) if allowed[fi].any()]
        fi_best = min(cand, key=lambda fi: resid[fi])
        rows = np.arange(len(grid_f))
        point_rows = [fi_best] * n_q
    else:
        rows = np.arange(len(grid_f), n_f)  # the given path: footprint f_given[qi] for q = grid_q[qi]
        point_rows = list(rows)
    q_ok = [qi for qi in range(n_q) if allowed[point_rows[qi], qi]] or list(range(n_q))
    q_mid = float(np.sqrt(grid_q[q_ok[0]] * grid_q[q_ok[-1]]))
    qi_best = min(q_ok, key=lambda qi: abs(math.log(grid_q[qi] / q_mid)))
    fi_point = point_rows[qi_best]
    estimate = float(dr0[fi_point, qi_best])
    # the interval: the union over the allowed points of the prior grid (the given values only: their points)
    prior_rows = np.arange(len(grid_f))
    sel = np.zeros((n_f, n_q), bool)
    sel[prior_rows] = allowed[prior_rows]
    if not sel.any():
        sel[prior_rows] = True
    gsel = None
    if f_given is not None:
        gsel = np.zeros((n_f, n_q), bool)
        gsel[point_rows, np.arange(n_q)] = True
        if (gsel & allowed).any():
            gsel &= allowed

    def union(low: np.ndarray, high: np.ndarray, point: float) -> tuple[float, float]:
        env = (float(low[sel].min()), float(high[sel].max()))
        if gsel is not None:
            env = (max(float(low[gsel].min()), env[0]), min(float(high[gsel].max()), env[1]))
        return min(env[0], point), max(env[1], point)

    ci = union(lo, hi, estimate)
    # the seeing angle in px, ρ = λ/(r0·ifov) = λ/(D·ifov)·D/r0: tilt (σ² ∝ q^(1/3) ρ^(5/3)) and blur (∝ ρ) both
    # measure it, so it varies as q^(-1/5) only over the λ/(D·ifov) prior where D/r0 varies as q^(-6/5)
    seeing = float(grid_q[qi_best]) * estimate
    seeing_ci = union(grid_q[None, :] * lo, grid_q[None, :] * hi, seeing)
    # what widens the interval most: each parameter's share of ln(hi/lo)
    width = {
        "the tile bootstrap": float(tiles_sd[fi_point]),
        "the clip-to-clip scatter": float(clip_sd[fi_point, qi_best]),
    }
    width.update({"little texture": extra.get("texture", 0.0)})
    width["a footprint below the calibrated 4 px"] = float(ext_sd[fi_point])
    spans = {k: 2 * Z90 * v for k, v in width.items()}
    spans["a tilt beyond the calibrated 3 px rms (the registration errs high)"] = Z90 * float(
        tilt_sd[fi_point, qi_best]
    )
    given = {"ifov_rad": optics.ifov_known, "path_length_m": optics.path_length_m is not None}
    if not optics.ifov_known:
        qs = grid_q[sel.any(0)]
        spans["unknown λ/(D·ifov) (give --ifov RAD)"] = 1.2 * math.log(qs.max() / qs.min()) if len(qs) else 0
    if optics.path_length_m is None:
        rows_used = prior_rows[sel[prior_rows].any(1)]
        per_f = [np.log(dr0[rows_used, qi].max() / dr0[rows_used, qi].min()) for qi in range(n_q) if len(rows_used)]
        spans["unknown path length (give --path-length M)"] = float(max(per_f)) if per_f else 0.0
    fit_best = np.unravel_index(best[fi_point], models.shape[1:4])
    vi, di, bi = fit_best
    q_est = float(grid_q[qi_best])
    out = {
        "dr0": estimate,
        "dr0_ci": [float(ci[0]), float(ci[1])],
        "seeing_px": seeing,
        "seeing_px_ci": [float(seeing_ci[0]), float(seeing_ci[1])],
        "dr0_log_sd": {
            "tiles": float(tiles_sd[fi_point]),
            "clip": float(clip_sd[fi_point, qi_best]),
            "footprint_below": float(ext_sd[fi_point]),
            "large_tilt_lower": float(tilt_sd[fi_point, qi_best]),  # the lower bound's only
            **extra,
        },
        "widened_by": max(spans, key=spans.get),
        "parameters": {
            "given": [k for k, v in given.items() if v],
            "marginalised": {
                **(
                    {}
                    if optics.ifov_known
                    else {
                        "lambda_over_d_px": {
                            "prior": list(Q_PRIOR),
                            "range_used": [float(grid_q[sel.any(0)].min()), float(grid_q[sel.any(0)].max())],
                            "from_blur": blur_used,
                        }
                    }
                ),
                **(
                    {}
                    if optics.path_length_m is not None
                    else {"footprint_px": {"prior": list(FOOTPRINT_PRIOR_PX), "path_prior_km": [0.3, 20.0]}}
                ),
                "wind_and_boiling": {
                    "wind_per_frame_D": [float(WIND_GRID[0]), float(WIND_GRID[-1])],
                    "boil": [float(BOIL_GRID[0]), float(BOIL_GRID[-1])],
                    "how": "fitted (profile)",
                },
            },
        },
        "lambda_over_d_px": q_est,
        "tilt_var_px2": float(0.1816 * q_est**2 * estimate ** (5 / 3)),
        "fit": {
            "footprint_px": float(fs[fi_point]),
            "footprint_per_px": float(1.0 / fs[fi_point]),
            "wind_per_frame_D": float(WIND_GRID[vi]),
            "wind_dir_deg": float(DIR_GRID[di]),
            "boil": float(BOIL_GRID[bi]),
        },
    }
    if blur is not None:
        out["blur"] = blur
    if optics.fps is not None:
        out["fit"]["wind_m_s"] = float(WIND_GRID[vi] * optics.fps * optics.aperture_m)
    if optics.path_length_m is None:
        ifov = optics.wavelength_m / (optics.aperture_m * q_est)
        out["fit"]["path_length_m_implied"] = float(optics.aperture_m / (fs[fi_point] * ifov))
    out.update(r0_cn2_theta0(estimate, optics))
    return out


__all__ = [
    "Optics",
    "as_optics",
    "estimate_from_sums",
    "lag_sums",
    "log_normal_interval",
    "measure_clip",
    "r0_cn2_theta0",
    "register_clip",
    "register_measurable",
    "registration_gain",
    "clip_log_sd",
    "short_exposure_width",
    "flow_variance_px2",
    "registration_dr0",
    "registration_tilt_variance",
]
