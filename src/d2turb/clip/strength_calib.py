"""The calibration of ``d2turb.clip.strength``: the registration gain's table (read by
``strength_fit.registration_gain``), the interval's terms and the prior ranges of what a user did not give, each with
where it was measured (docs/measure.md); ``d2turb.clip.strength`` re-exports them."""

from __future__ import annotations

import math

import numpy as np

from d2turb.sim.tilt import tilt_variance_px2

# registration gain ε(r, D/r0, footprint): DIS-measured / true differential-tilt power at separation r px, from
# simulated calibration clips (crops of train-split images, never the validation images: bsds500, outdoor views of
# camvid, strecha_mvs, sfm_landmarks, the 32 least textured train crops, and every "field" geometry at D/r0 3.5 and
# 4.5; 256², 64 frames, wind 1–3 m/s, the default optics and the "field" bank; docs/measure.md,
# benchmarks/measure/fitgain.py): a smooth least-squares model of ln ε in ln r, ln footprint and D/r0 tabulated here.
# Index [footprint][D/r0][separation]; linear in ln footprint, D/r0 and ln r between the nodes, clamped outside. The
# footprint is the tilt's correlation scale D/(ifov·L) in px (38 px for the default optics).
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
# blind λ/(D·ifov): the fused (registered, averaged) frame's blur σ_b (clip.blur.estimate_blur) against the optical
# short-exposure blur q·s(D/r0) (s: the Gaussian-equivalent width of the tilt-removed OTF of sim.otf in units of λ/D,
# :func:`short_exposure_width`). On simulated clips (the oracle: the simulator's known q and D/r0; q 2–3, D/r0 2–4,
# docs/measure.md) σ_b = c·q·s(D/r0) with c 0.48–0.57; BLUR_GAIN is that range widened. Real clips add blur the
# optics model leaves out (lens, sensor, codec): σ_b up to BLUR_EXCESS_MAX times the optical part. A grid point
# (q, D/r0) is kept when [c_lo·q·s, c_hi·q·s·BLUR_EXCESS_MAX] meets the blur's 90 % interval. Tilt and blur both grow
# like λ/r0 when D/r0 is large, so the blur fixes q for a given D/r0 rather than D/r0 itself: it narrows the prior,
# it does not replace the optics.
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
CALIBRATED_TILT_RMS_PX = math.sqrt(float(tilt_variance_px2(GAIN_DR0[-1], 2.0)))
LARGE_TILT_LOG_SD = 0.96
# little usable area: an extra log-sd LOW_TEXTURE_LOG_SD·sqrt(TEXTURED_FULL/valid − 1) below TEXTURED_FULL
# (uncalibrated widening; the tile bootstrap already widens with fewer pairs)
TEXTURED_FULL = 0.15
LOW_TEXTURE_LOG_SD = 0.1
MAX_SPAN = 3.0  # a 90 % interval wider (hi/lo) gets a note naming what narrows it; D/r0 is "determined" within it
NEGLIGIBLE_DR0 = 0.3  # ... or when its upper bound is below this: "no measurable turbulence" is an answer


def log_normal_interval(estimate: float, log_sds, z: float = Z90) -> tuple[float, float]:
    """``estimate``·exp(∓z·s) with s the quadrature sum of the independent log-sds ``log_sds`` (a 90 % interval
    with the default z, the t quantile of the calibrated clip term, when ln of the estimate is normal about ln of
    the truth)."""
    s = math.sqrt(sum(float(v) ** 2 for v in log_sds))
    return estimate * math.exp(-z * s), estimate * math.exp(z * s)


def texture_log_sd(valid_fraction: float) -> float:
    """The uncalibrated widening for little usable area (sd of ln D/r0): 0 from ``TEXTURED_FULL`` up."""
    if valid_fraction >= TEXTURED_FULL:
        return 0.0
    return LOW_TEXTURE_LOG_SD * math.sqrt(TEXTURED_FULL / max(valid_fraction, 1e-6) - 1.0)
