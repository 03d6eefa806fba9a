"""What a parameter set means physically: r0, Cn², θ0, the tilt's spread and correlation scale, the sampling."""

from __future__ import annotations

from d2turb.sim.geometry import footprint_px
from d2turb.sim.params import TurbulenceParams, cn2_spherical, dr0_bin, isoplanatic_angle
from d2turb.sim.simulator import Simulator


def derived_quantities(params: TurbulenceParams, mean_modulation: float | None = None) -> dict:
    """The physical quantities of ``params`` (D/r0 resolved), as the page shows them.

    Args:
        params: the simulator's parameters.
        mean_modulation: the mean depth modulation M of an image, if any.

    Returns:
        dict with dr0, bin, r0_m, cn2 (the constant, spherical-wave value that gives this r0), theta0_urad /
        theta0_px (plane-wave isoplanatic angle, :func:`~d2turb.sim.params.isoplanatic_angle`), tilt_sigma_px (per
        axis, where M = 1; the simulator's own scale), footprint_px (tilt correlation scale), samples_per_lambda_d
        (q = λ/(D·ifov), 2 = Nyquist), ifov_urad; with ``mean_modulation`` also mean_modulation and
        tilt_sigma_px_mean_m (σ at the mean M: Δ = M·Δ0, Eq. 5).
    """
    lam, length = params.reference_wavelength, params.path_length_m
    r0 = params.r0_m
    cn2 = cn2_spherical(r0, length, lam)
    theta0 = isoplanatic_angle(cn2, length, lam, wave="plane")
    sim = Simulator(params)
    sigma = sim.tilt_std * sim.px_per_a2 * params.dr0 ** (5 / 6)
    out = {
        "dr0": params.dr0,
        "bin": dr0_bin(params.dr0),
        "r0_m": r0,
        "cn2": cn2,
        "theta0_urad": theta0 * 1e6,
        "theta0_px": theta0 / params.ifov_rad,
        "tilt_sigma_px": sigma,
        "footprint_px": footprint_px(params),
        "samples_per_lambda_d": params.lambda_over_d_px,
        "ifov_urad": params.ifov_rad * 1e6,
    }
    if mean_modulation is not None:
        out["mean_modulation"] = float(mean_modulation)
        out["tilt_sigma_px_mean_m"] = sigma * float(mean_modulation)
    return out
