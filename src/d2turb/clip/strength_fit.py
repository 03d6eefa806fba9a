"""The inversion behind :func:`d2turb.clip.strength.measure_clip`: from the structure sums of the registered motion
to the seeing angle ρ = λ/(r0·ifov) and D/r0 with their 90 % intervals (docs/measure.md).

:func:`estimate_from_sums` runs its three steps in order, each in its own module and none calling back:

1. the fit, here (:func:`fit_sums`, one :class:`Fit`): the unit models of the differential-tilt structure function on
   the nuisance grid (:func:`structure_models`), σ² per node of the prior grid (:class:`PriorGrid`) with the
   registration gain at a fixed point (:func:`fit_grid`, :func:`registration_gain`), the tile bootstrap
   (:func:`bootstrap_log_sd`);
2. the interval, ``d2turb.clip.strength_interval`` (one ``Interval``): the error budget, the λ/(D·ifov) nodes the
   fused frame's blur allows, the point and the nodes the interval is the union of, what widens it most;
3. the estimate, ``d2turb.clip.strength_result`` (one ``StrengthEstimate``, measure.json's keys).

The calibration constants are in ``d2turb.clip.strength_calib``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from d2turb.clip.strength_calib import (
    BOIL_GRID,
    DIR_GRID,
    FOOTPRINT_PRIOR_PX,
    FOOTPRINT_PX_GRID,
    GAIN_DR0,
    GAIN_FOOTPRINT_PX,
    GAIN_SEPARATIONS_PX,
    GAIN_TABLE,
    Q_GRID,
    WIND_GRID,
)
from d2turb.clip.strength_interval import interval_of
from d2turb.clip.strength_result import StrengthEstimate, strength_estimate
from d2turb.sim.params import Optics, as_optics, r0_cn2_theta0
from d2turb.sim.tilt import differential_tilt_covariance, dr0_from_tilt_variance, tilt_variance_px2


# ---- the fit ----------------------------------------------------------------------------------------------------
def structure_models(series, t_len: int, footprints_per_px, geometry="path") -> np.ndarray:
    """Unit structure-function models 2[G(0) − G(τ)] (F, V, Dir, B, J, T) on the nuisance grid, for the tilt
    correlation scales ``footprints_per_px`` = ifov·L/D (F,) and the ``series`` (separation, orientation, component)
    of :func:`d2turb.clip.motion.lag_sums`."""
    seps = sorted({r for r, _, _ in series})
    lags = np.arange(t_len)
    out = np.zeros((len(footprints_per_px), len(WIND_GRID), len(DIR_GRID), len(BOIL_GRID), len(series), t_len))
    boil_f = np.array([(1 - b) ** (lags / 2) for b in BOIL_GRID])  # (B, T)
    for fi, a in enumerate(footprints_per_px):
        for vi, v in enumerate(WIND_GRID):
            for di, d in enumerate(DIR_GRID):
                vec = [[r, 0] for r in seps] + [[0, r] for r in seps]
                g = differential_tilt_covariance(vec, lags, a, v, d, 0.0, geometry)  # (2S, 2, T)
                for j, (r, orient, comp) in enumerate(series):
                    gj = g[seps.index(r) + orient * len(seps), comp]
                    out[fi, vi, di, :, j] = 2 * (gj[0] - gj[None] * boil_f)
    return out


def _sig2_and_residual(num, pairs, t_len, models, gains):
    """σ² and the weighted relative residual on the whole grid (F, V, Dir, B): σ² a ratio of sums per grid point."""
    lags = np.arange(t_len)
    w = pairs[:, None] * (t_len - lags)[None]  # pair-lags per (j, τ)
    w[:, 0] = 0
    with np.errstate(invalid="ignore", divide="ignore"):
        data = np.where(w > 0, num / np.maximum(w, 1), 0.0)  # D̂_j(τ)
    m = models * np.asarray(gains, np.float64)[:, None, None, None, :, None]
    sig2 = (w * data).sum((-1, -2)) / np.maximum((w * m).sum((-1, -2)), 1e-300)
    fit = sig2[..., None, None] * m
    resid = (w * (data - fit) ** 2 / np.maximum(fit, 1e-12) ** 2).sum((-1, -2))
    return sig2, resid


def fit_nuisance(num, pairs, t_len, models, gains):
    """(σ², index of the best nuisance point) from summed ``num`` (J, T) and ``pairs`` (J,); ``gains`` (F, J): the
    registration gain per footprint of ``models`` and series."""
    sig2, resid = _sig2_and_residual(num, pairs, t_len, models, gains)
    best = np.unravel_index(np.argmin(resid), resid.shape)
    return float(sig2[best]), best


def fit_per_footprint(num, pairs, t_len, models, gains):
    """σ² (F,), the weighted residual (F,) and the flat index of the best nuisance point (wind, direction, boiling)
    (F,) of each footprint of ``models`` (F, V, Dir, B, J, T); ``gains`` (F, J)."""
    sig2, resid = _sig2_and_residual(num, pairs, t_len, models, gains)
    flat = resid.reshape(len(resid), -1)
    best = flat.argmin(1)
    return sig2.reshape(len(sig2), -1)[np.arange(len(sig2)), best], flat[np.arange(len(flat)), best], best


def registration_gain(sep_px, dr0: float, footprint_px: float = 38.1) -> np.ndarray:
    """ε, the registration's share of the differential-tilt power, for separations ``sep_px`` at strength ``dr0`` and
    tilt correlation scale ``footprint_px`` = D/(ifov·L), from the calibrated ``GAIN_TABLE`` (linear in ln footprint,
    D/r0 and ln r; clamped outside the table)."""
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


@dataclass(frozen=True)
class PriorGrid:
    """The nodes of what was not given: footprints ``fs`` (F,) in px, of which the first ``n_prior`` are the prior's
    (the rest: the given path's footprint per q), λ/(D·ifov) ``q`` (Q,) in px (one node when ifov was given)."""

    fs: np.ndarray
    q: np.ndarray
    n_prior: int
    path_given: bool

    @classmethod
    def of(cls, optics: Optics) -> PriorGrid:
        q = np.array([optics.lambda_over_d_px]) if optics.ifov_known else Q_GRID
        prior = np.array(FOOTPRINT_PX_GRID)
        if optics.path_length_m is None:
            return cls(prior, q, len(prior), False)
        f_of_q = np.clip(optics.aperture_m**2 * q / (optics.wavelength_m * optics.path_length_m), *FOOTPRINT_PRIOR_PX)
        return cls(np.concatenate([prior, f_of_q]), q, len(prior), True)

    def gains(self, seps, dr0_per_f) -> np.ndarray:
        """(F, J): the registration gain of each footprint node at its strength ``dr0_per_f`` (F,)."""
        return np.stack([registration_gain(seps, dr0_per_f[fi], self.fs[fi]) for fi in range(len(self.fs))])


def fit_grid(num, pairs, seps, t_len, models, grid: PriorGrid) -> np.ndarray:
    """D/r0 (F, Q) per node: σ² by :func:`fit_per_footprint` with the registration gain at the node's own strength
    (a fixed point, three steps from 2.5; the gain depends on the strength)."""
    dr0 = np.full((len(grid.fs), len(grid.q)), 2.5)
    tot_num, tot_pairs = num.sum(0), pairs.sum(0)
    for qi, q in enumerate(grid.q):
        for _ in range(3):
            sig2 = fit_per_footprint(tot_num, tot_pairs, t_len, models, grid.gains(seps, dr0[:, qi]))[0]
            dr0[:, qi] = dr0_from_tilt_variance(np.maximum(sig2, 0.0), float(q))
    return dr0


def bootstrap_log_sd(num, pairs, t_len, models, gains, resamples: int, seed: int) -> np.ndarray:
    """The sd of ln D/r0 per footprint (F,) over ``resamples`` bootstrap resamples of the spatial tiles of ``num``
    (tiles, J, T), the fit redone per resample at fixed ``gains`` (ln D/r0 = 3/5 ln σ² + const: its sd does not
    depend on λ/(D·ifov)); 0 without resamples."""
    rng = np.random.default_rng(seed)
    n_tiles = num.shape[0]
    boot = []
    for _ in range(resamples):
        pick = rng.integers(0, n_tiles, n_tiles)
        boot.append(fit_per_footprint(num[pick].sum(0), pairs[pick].sum(0), t_len, models, gains)[0])
    if not boot:
        return np.zeros(len(gains))
    with np.errstate(divide="ignore", invalid="ignore"):
        sd = np.std(0.6 * np.log(np.array(boot)), axis=0)
    return np.where(np.isfinite(sd), sd, 0.0)


@dataclass(frozen=True)
class Fit:
    """What the fit of one set of structure sums gives (:func:`fit_sums`): D/r0 per node ``dr0`` (F, Q), the sd of
    its log over the tile bootstrap ``tiles_sd`` (F,), and per footprint the weighted residual ``resid`` (F,) and the
    flat index ``best`` (F,) of the best nuisance point, on the nuisance grid ``nuisance_shape`` (V, Dir, B), from
    clip windows of ``t_len`` frames; ``tilt_var_px2`` (F, Q): the Z-tilt variance per axis that ``dr0`` gives at
    each node's λ/(D·ifov)."""

    grid: PriorGrid
    dr0: np.ndarray
    tiles_sd: np.ndarray
    resid: np.ndarray
    best: np.ndarray
    nuisance_shape: tuple
    t_len: int
    tilt_var_px2: np.ndarray


def fit_sums(num, pairs, series, grid: PriorGrid, bootstrap: int, seed: int, cache: dict) -> Fit:
    """:class:`Fit` of the sums ``num`` (tiles, J, T), ``pairs`` (tiles, J) of the ``series`` of ``lag_sums`` on the
    prior ``grid``; the structure models are kept in ``cache`` between calls (windows of one clip)."""
    t_len = num.shape[-1]
    key = (t_len, tuple(np.round(grid.fs, 9)))
    if key not in cache:
        cache[key] = structure_models(series, t_len, list(1.0 / grid.fs))
    models = cache[key]
    seps = [r for r, _, _ in series]
    dr0 = fit_grid(num, pairs, seps, t_len, models, grid)
    gains = grid.gains(seps, dr0[:, int(np.argmin(np.abs(np.log(grid.q / 2.0))))])  # at the central q
    tiles_sd = bootstrap_log_sd(num, pairs, t_len, models, gains, bootstrap, seed)
    _, resid, best = fit_per_footprint(num.sum(0), pairs.sum(0), t_len, models, gains)
    return Fit(grid, dr0, tiles_sd, resid, best, models.shape[1:4], t_len, tilt_variance_px2(dr0, grid.q[None, :]))


def estimate_from_sums(
    num, pairs, series, optics: Optics, bootstrap=200, seed=0, cache=None, blur=None, extra=None
) -> StrengthEstimate:
    """The fit, the interval and the estimate from the structure sums of :func:`d2turb.clip.motion.lag_sums` (what
    :func:`~d2turb.clip.strength.measure_clip` does after the registration).

    Args:
        num, pairs, series: the sums (tiles, J, T), (tiles, J) and the J series of ``lag_sums``.
        optics: an :class:`Optics` or what :func:`as_optics` takes; what it does not give is marginalised.
        bootstrap: tile resamples for the interval. seed: their random seed.
        cache: a dict that keeps the structure models between calls (windows of one clip).
        blur: the fused frame's blur estimate (``sigma_ci``, ``confident``) for the blind λ/(D·ifov).
        extra: named extra log-sds of the interval (``texture``).

    Returns:
        A :class:`StrengthEstimate`.
    """
    optics = as_optics(optics)
    fit = fit_sums(num, pairs, series, PriorGrid.of(optics), bootstrap, seed, {} if cache is None else cache)
    interval = interval_of(fit, optics, blur, extra or {})
    phys = (
        r0_cn2_theta0(interval.dr0, optics) if optics.ifov_known else {"r0_m": None, "cn2": None, "theta0_urad": None}
    )
    return strength_estimate(fit, interval, optics, blur, phys)
