"""The result of the strength inversion (its last step, after ``d2turb.clip.strength_fit`` and
``d2turb.clip.strength_interval``): one :class:`StrengthEstimate` per clip or window, measure.json's dict
(:func:`measure_record`), and the estimate in words (:func:`estimate_words`, :func:`interval_note`,
:func:`undetermined_dr0`: what ``measure`` prints and ``restore`` says of a measured D/r0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from d2turb.clip.strength_calib import (
    BOIL_GRID,
    DIR_GRID,
    FOOTPRINT_PRIOR_PX,
    MAX_SPAN,
    NEGLIGIBLE_DR0,
    Q_PRIOR,
    WIND_GRID,
)
from d2turb.sim.params import Optics

if TYPE_CHECKING:
    from d2turb.clip.strength_fit import Fit, PriorGrid
    from d2turb.clip.strength_interval import Choice, Interval

# how a user narrows an interval (issue 53): the parameter to give, in the flags of `measure` and `restore`
HOW_TO_GIVE = {
    "ifov_rad": "--ifov RAD (the camera's pixel pitch over its focal length)",
    "path_length_m": "--path-length M (the distance to the scene)",
}
# the other terms of an interval, in words (strength_fit.TERMS)
TERM_WORDS = {
    "tiles": "the spatial sampling of this crop (more textured area or more frames narrow it)",
    "clip": "the calibrated clip-to-clip scatter",
    "texture": "little texture",
    "footprint_below": "a tilt correlation scale below the calibrated 4 px",
    "large_tilt_lower": "a tilt beyond the calibrated 3 px rms (the registration errs high)",
}
QUANTITY_WORDS = {"seeing_px": "the seeing angle ρ = λ/(r0·ifov)", "dr0": "D/r0"}
UNITS = {"seeing_px": "px", "dr0": ""}


def _parameters(optics: Optics, grid: PriorGrid, choice: Choice, blur_used: bool) -> dict:
    """measure.json's ``parameters``: what was given, and what was marginalised over which range."""
    given = {"ifov_rad": optics.ifov_known, "path_length_m": optics.path_length_m is not None}
    marginalised = {}
    if not optics.ifov_known:
        used = grid.q[choice.sel.any(0)]
        marginalised["lambda_over_d_px"] = {
            "prior": list(Q_PRIOR),
            "range_used": [float(used.min()), float(used.max())],
            "from_blur": blur_used,
        }
    if optics.path_length_m is None:
        marginalised["footprint_px"] = {"prior": list(FOOTPRINT_PRIOR_PX), "path_prior_km": [0.3, 20.0]}
    marginalised["wind_and_boiling"] = {
        "wind_per_frame_D": [float(WIND_GRID[0]), float(WIND_GRID[-1])],
        "boil": [float(BOIL_GRID[0]), float(BOIL_GRID[-1])],
        "how": "fitted (profile)",
    }
    return {"given": [k for k, v in given.items() if v], "marginalised": marginalised, "blur_used": blur_used}


def _fitted(optics: Optics, grid: PriorGrid, choice: Choice, best_flat: int, shape) -> dict:
    """measure.json's ``fit``: the point's footprint and its fitted nuisance parameters."""
    vi, di, bi = np.unravel_index(best_flat, shape)
    f_px = float(grid.fs[choice.fi])
    out = {
        "footprint_px": f_px,
        "footprint_per_px": float(1.0 / f_px),
        "wind_per_frame_D": float(WIND_GRID[vi]),
        "wind_dir_deg": float(DIR_GRID[di]),
        "boil": float(BOIL_GRID[bi]),
    }
    if optics.fps is not None:
        out["wind_m_s"] = float(WIND_GRID[vi] * optics.fps * optics.aperture_m)
    if optics.path_length_m is None:
        ifov = optics.wavelength_m / (optics.aperture_m * float(grid.q[choice.qi]))
        out["path_length_m_implied"] = float(optics.aperture_m / (f_px * ifov))
    return out


@dataclass
class StrengthEstimate:
    """What a clip's structure sums say (``strength_fit.estimate_from_sums``); :meth:`to_dict` gives measure.json's
    keys.

    ``seeing_px`` = λ/(r0·ifov), the seeing angle in px, and ``dr0`` with their 90 % intervals; ``dr0_determined``:
    D/r0's interval within ``MAX_SPAN`` (or below ``NEGLIGIBLE_DR0``); ``r0_m``, ``cn2``, ``theta0_urad`` as the optics
    allow (None without ifov: r0 = λ/(ρ·ifov); Cn² and θ0 also need the path); ``narrowing``: per quantity, its span
    and what narrows it most (:func:`~d2turb.clip.strength_interval.narrowing`)."""

    seeing_px: float
    seeing_px_ci: list
    dr0: float
    dr0_ci: list
    dr0_determined: bool
    dr0_log_sd: dict
    r0_m: float | None
    cn2: float | None
    theta0_urad: float | None
    widened_by: str
    narrowing: dict
    parameters: dict
    lambda_over_d_px: float
    tilt_var_px2: float
    fit: dict
    blur: dict | None = None

    def to_dict(self) -> dict:
        out = dict(self.__dict__)
        if out["blur"] is None:
            del out["blur"]
        return out


def strength_estimate(fit: Fit, interval: Interval, optics: Optics, blur: dict | None, phys: dict) -> StrengthEstimate:
    """The :class:`StrengthEstimate` of a fit and its interval; ``phys``: r0_m, cn2, theta0_urad (None where the
    optics do not give them)."""
    ci, seeing_ci, q, estimate = interval.dr0_ci, interval.seeing_px_ci, interval.lambda_over_d_px, interval.dr0
    span = ci[1] / ci[0] if ci[0] > 0 else math.inf
    return StrengthEstimate(
        seeing_px=interval.seeing_px,
        seeing_px_ci=[float(seeing_ci[0]), float(seeing_ci[1])],
        dr0=estimate,
        dr0_ci=[float(ci[0]), float(ci[1])],
        dr0_determined=bool(span <= MAX_SPAN or ci[1] < NEGLIGIBLE_DR0),
        dr0_log_sd=interval.log_sd,
        widened_by=interval.widened_by,
        narrowing=interval.narrowing,
        parameters=_parameters(optics, fit.grid, interval.choice, interval.blur_used),
        lambda_over_d_px=q,
        tilt_var_px2=float(0.1816 * q**2 * estimate ** (5 / 3)),
        fit=_fitted(optics, fit.grid, interval.choice, int(fit.best[interval.choice.fi]), fit.nuisance_shape),
        blur=blur,
        **phys,
    )


def measure_record(whole: StrengthEstimate, diag: dict, windows: list, inputs: dict) -> dict:
    """measure.json's dict: the clip's estimate (``whole``), the registration's diagnostics ``diag``, the ``answer``,
    the estimates of the clip's ``windows`` [(start frame, frames, StrengthEstimate)] (None: no windows asked for)
    and the ``inputs``."""
    result = whole.to_dict()
    result.update(diag)
    key = answer_quantity(result)
    result["answer"] = {"quantity": key, "value": result[key], "ci": result[f"{key}_ci"], "unit": UNITS[key]}
    if windows is not None:
        keys = ("seeing_px", "seeing_px_ci", "dr0", "dr0_ci")
        result["windows"] = [
            {"start_frame": s, "frames": n, **{k: getattr(est, k) for k in keys}} for s, n, est in windows
        ]
    result["inputs"] = inputs
    return result


def answer_quantity(result: dict) -> str:
    """The key of what ``result`` answers with: ``dr0`` when ifov_rad was given, else ``seeing_px``."""
    return "dr0" if "ifov_rad" in result["parameters"]["given"] else "seeing_px"


def interval_note(result: dict, key: str | None = None) -> str | None:
    """One sentence when the 90 % interval of ``key`` (default :func:`answer_quantity`) spans more than
    ``MAX_SPAN``: its span and what narrows it most (a parameter to give, with the span it would have, or the term
    that widens it); None within ``MAX_SPAN``."""
    key = key or answer_quantity(result)
    n = result["narrowing"][key]
    if n["span"] <= MAX_SPAN:
        return None
    text = f"the 90 % interval of {QUANTITY_WORDS[key]} spans {n['span']:.1f}x"
    if n["by"] is not None:
        return text + f"; giving {HOW_TO_GIVE[n['by']]} narrows it most (to about {n['span_with']:.1f}x)"
    return text + f", widened most by {TERM_WORDS[n['widened_most_by']]}"


def estimate_words(result: dict) -> str:
    """The estimate in measure's terms: D/r0 and ρ with the camera's ifov; without it ρ, then D/r0 at the
    λ/(D·ifov) the estimate holds at."""
    (lo, hi), (s_lo, s_hi) = result["dr0_ci"], result["seeing_px_ci"]
    seeing = f"seeing angle ρ = {result['seeing_px']:.3g} px [{s_lo:.3g}, {s_hi:.3g}]"
    if answer_quantity(result) == "dr0":
        return f"D/r0 {result['dr0']:.3g} [{lo:.3g}, {hi:.3g}], {seeing}"
    q = result["lambda_over_d_px"]
    return f"{seeing}; D/r0 {result['dr0']:.3g} [{lo:.3g}, {hi:.3g}] at its λ/(D·ifov) {q:.3g} px"


def undetermined_dr0(result: dict) -> str:
    """Why D/r0 is not determined (``dr0_determined`` False), in the user's terms: what was measured, what to give."""
    lo, hi = result["dr0_ci"]
    if "ifov_rad" not in result["parameters"]["given"]:
        s_lo, s_hi = result["seeing_px_ci"]
        return (
            f"without the camera the clip gives the seeing angle ρ = λ/(r0·ifov) = {result['seeing_px']:.2f} px "
            f"[{s_lo:.2f}, {s_hi:.2f}] (90 %), and D/r0 only within [{lo:.2f}, {hi:.2f}]: give "
            + HOW_TO_GIVE["ifov_rad"]
        )
    return f"D/r0 = {result['dr0']:.2f} [{lo:.2f}, {hi:.2f}] (90 %): {interval_note(result, 'dr0')}"
