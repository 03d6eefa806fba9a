"""Turbulence strength from a clip of a static scene: the seeing angle in pixels ρ = λ/(r0·ifov), and as the optics
allow D/r0, r0, Cn² and the isoplanatic angle θ0, each with a 90 % interval (docs/measure.md).

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
rms above the calibrated 3 px its lower bound (calibrated: there the registration errs high, ``LARGE_TILT_LOG_SD``).

What is answered (issue 53): tilt and blur both measure ρ, so ρ is the answer without the optics; D/r0 = ρ/(λ/(D·ifov))
needs ifov. An estimate is always given with its interval, however wide; an interval wider than ``MAX_SPAN`` comes with
what narrows it most (:func:`interval_note`). Only a clip with nothing to estimate is refused: too few frames, no
texture, frames that do not register onto one static scene.

Code. :func:`measure_clip` runs the steps in order, none calling back: the frames to grey, their registration and
the structure sums (``d2turb.clip.motion``), the fit (``strength_fit``), the interval (``strength_interval``), the
result and its words (``strength_result``); the calibration constants are ``strength_calib``'s. The names of those
modules stay importable from here (benchmarks, tests).
"""

from __future__ import annotations

import numpy as np

from d2turb.clip.blur import estimate_blur
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
from d2turb.clip.strength_calib import (  # the calibration (benchmarks, tests read it from here)
    BLUR_EXCESS_MAX,
    BLUR_GAIN,
    CALIBRATED_TILT_RMS_PX,
    CLIP_DOF,
    CLIP_FRAMES,
    CLIP_LOG_SD,
    CLIP_WINDOW_VAR,
    EXTRAPOLATION_LOG_SD,
    FOOTPRINT_PRIOR_PX,
    FOOTPRINT_PX_GRID,
    GAIN_DR0,
    GAIN_FOOTPRINT_PX,
    GAIN_SEPARATIONS_PX,
    GAIN_TABLE,
    LARGE_TILT_LOG_SD,
    MAX_SPAN,
    NEGLIGIBLE_DR0,
    Q_GRID,
    Q_PRIOR,
    Z90,
    log_normal_interval,
    texture_log_sd,
)
from d2turb.clip.strength_fit import (
    estimate_from_sums,
    fit_nuisance,
    fit_per_footprint,
    registration_gain,
    structure_models,
)
from d2turb.clip.strength_interval import clip_log_sd
from d2turb.clip.strength_result import (
    HOW_TO_GIVE,
    QUANTITY_WORDS,
    TERM_WORDS,
    UNITS,
    StrengthEstimate,
    answer_quantity,
    estimate_words,
    interval_note,
    measure_record,
    undetermined_dr0,
)
from d2turb.errors import D2TurbError
from d2turb.sim.otf import short_exposure_width
from d2turb.sim.params import Optics, as_optics, r0_cn2_theta0


def measure_clip(
    frames,
    optics: Optics | dict | None = None,
    window: int | None = None,
    bootstrap: int = 200,
    max_size: int = 320,
    seed: int = 0,
    preset: str = "medium",
    blind: bool = True,
) -> dict:
    """Measure the seeing angle in pixels ρ = λ/(r0·ifov), D/r0, and with the optics r0 (and with a path length Cn²,
    θ0) from the frames of a static scene.

    Every pixel-level parameter the optics do not give is marginalised over its prior range (``Q_PRIOR`` for
    λ/(D·ifov) without ifov_rad, narrowed by the blind estimate from the clip's blur; ``FOOTPRINT_PRIOR_PX`` for the
    tilt's correlation scale without path_length_m): the 90 % interval is the union of the intervals over the prior
    grid, so that giving a parameter can only narrow it (the given interval is intersected with it, which moves its
    bounds by at most the grid's interpolation). ``result["parameters"]`` says which were given and which were
    marginalised, with their ranges. An estimate is returned however wide its interval (``narrowing`` says what
    narrows it, :func:`interval_note` in words); only a clip with nothing to estimate raises.

    Args:
        frames: a sequence of (3,H,W) tensors or (H,W[,C]) arrays in [0, 1], one per frame.
        optics: :class:`Optics`, a dict of its fields (aperture_m, wavelength_m, ifov_rad, path_length_m, fps) or
            a ``TurbulenceParams`` (its D/r0 is ignored; its ifov and path count as given).
        window: frames per window for a series of estimates over time (None: the whole clip only).
        bootstrap: resamples for the 90 % interval. max_size: the centre crop analysed (px per side).
        blind: use the blur of the fused frame: the (λ/(D·ifov), D/r0) nodes its optical blur allows (without ifov_rad
            it narrows λ/(D·ifov), with it the footprints and D/r0; a given ifov then never moves the interval
            outside the blind one).

    Returns:
        A dict (:meth:`StrengthEstimate.to_dict` and the registration's diagnostics): ``answer`` (the quantity
        answered with, ``seeing_px`` without ifov_rad and ``dr0`` with it, its value and 90 % ``ci``), ``seeing_px``
        and its ``seeing_px_ci``; ``dr0``, ``dr0_ci`` and ``dr0_determined`` (its interval within ``MAX_SPAN``:
        False without ifov_rad as a rule); ``r0_m`` (None without ifov_rad), ``cn2`` and ``theta0_urad`` (None
        without a path length too); ``narrowing`` (per quantity: span, the parameter that narrows it most),
        ``parameters`` (given, marginalised), ``widened_by``, ``windows``, ``inputs``, the diagnostics.
    Shape:
        - frames: N ≥ 8 (``MIN_FRAMES``) frames of :math:`(3, H, W)`, :math:`(H, W)` or :math:`(H, W, C)`.
    Raises:
        D2TurbError: a clip with nothing to estimate (too few frames, frames of different sizes or too small, no
        texture, frames that do not register onto one static scene) or bad optics.
    """
    optics = as_optics(optics)
    gray = gray_frames(frames)
    if window is not None and (int(window) < MIN_FRAMES or int(window) > len(gray)):
        raise D2TurbError(f"window must be between {MIN_FRAMES} and the {len(gray)} frames of the clip, got {window}")
    gray, crop = centre_crop(gray, max_size)
    flows, mask, diag = register_measurable(gray, preset)
    fused = diag.pop("_fused")
    seps = separations_for(*mask.shape)
    blur = _fused_blur(fused) if blind else None
    extra = {"texture": texture_log_sd(diag["valid_fraction"])}
    # the clip, then its windows: the same steps on each (the structure models computed once per length)
    starts = range(0, len(gray) - int(window) + 1, int(window)) if window else ()
    spans = [(0, len(gray)), *((s, int(window)) for s in starts)]
    models: dict = {}  # the structure models, computed once per length
    estimates = [
        estimate_from_sums(*lag_sums(flows[s : s + n], mask, seps), optics, bootstrap, seed, models, blur, extra)
        for s, n in spans
    ]
    inputs = {
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
    windows = [(s, n, est) for (s, n), est in zip(spans[1:], estimates[1:])] if window else None
    return measure_record(estimates[0], diag, windows, inputs)


def _fused_blur(fused: np.ndarray) -> dict | None:
    """The fused frame's blur (clip.blur.estimate_blur) as measure.json's ``blur``; None for frames below 32 px."""
    if min(fused.shape) < 32:
        return None
    est = estimate_blur(np.clip(fused / 255.0, 0, 1).astype(np.float32))
    blur = {"sigma_px": est.sigma_px, "sigma_ci": list(est.sigma_ci), "confident": est.confident}
    if not est.confident:
        blur["reason"] = est.reason
    return blur


__all__ = [
    "BLUR_EXCESS_MAX",
    "BLUR_GAIN",
    "CALIBRATED_TILT_RMS_PX",
    "CLIP_DOF",
    "CLIP_FRAMES",
    "CLIP_LOG_SD",
    "CLIP_WINDOW_VAR",
    "EXTRAPOLATION_LOG_SD",
    "FOOTPRINT_PRIOR_PX",
    "FOOTPRINT_PX_GRID",
    "GAIN_DR0",
    "GAIN_FOOTPRINT_PX",
    "GAIN_SEPARATIONS_PX",
    "GAIN_TABLE",
    "HOW_TO_GIVE",
    "LARGE_TILT_LOG_SD",
    "MAX_SPAN",
    "MIN_FRAMES",
    "NEGLIGIBLE_DR0",
    "Optics",
    "Q_GRID",
    "Q_PRIOR",
    "QUANTITY_WORDS",
    "StrengthEstimate",
    "TERM_WORDS",
    "UNITS",
    "Z90",
    "answer_quantity",
    "estimate_words",
    "as_optics",
    "centre_crop",
    "clip_log_sd",
    "estimate_from_sums",
    "fit_nuisance",
    "fit_per_footprint",
    "flow_variance_px2",
    "gray_frames",
    "interval_note",
    "lag_sums",
    "log_normal_interval",
    "measure_clip",
    "measure_record",
    "r0_cn2_theta0",
    "register_clip",
    "register_measurable",
    "registration_dr0",
    "registration_gain",
    "registration_tilt_variance",
    "separations_for",
    "short_exposure_width",
    "structure_models",
    "texture_log_sd",
    "undetermined_dr0",
]
