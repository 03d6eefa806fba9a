"""The inversion behind :func:`d2turb.clip.strength.measure_clip`: from the structure sums of the registered motion
to the seeing angle ρ = λ/(r0·ifov) and D/r0 with their 90 % intervals (docs/measure.md).

Its steps, each a function: the unit models of the differential-tilt structure function on the nuisance grid
(:func:`structure_models`), the fit of σ² per node of the prior grid with the registration gain at a fixed point
(:func:`fit_grid`), the tile bootstrap (:func:`bootstrap_log_sd`), the interval's error budget
(:func:`error_budget`), the λ/(D·ifov) nodes the fused frame's blur allows (:func:`blur_allowed`), the point and the
nodes the interval is the union of (:func:`choose_point`), and what widens each interval most
(:func:`narrowing`). :func:`estimate_from_sums` runs them and returns one :class:`StrengthEstimate`. The calibration
constants are in ``d2turb.clip.strength_calib``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from d2turb.clip.strength_calib import (
    BLUR_EXCESS_MAX,
    BLUR_GAIN,
    BOIL_GRID,
    CALIBRATED_TILT_RMS_PX,
    DIR_GRID,
    EXTRAPOLATION_LOG_SD,
    FOOTPRINT_PRIOR_PX,
    FOOTPRINT_PX_GRID,
    GAIN_FOOTPRINT_PX,
    LARGE_TILT_LOG_SD,
    MAX_SPAN,
    NEGLIGIBLE_DR0,
    Q_GRID,
    Q_PRIOR,
    WIND_GRID,
    Z90,
    clip_log_sd,
    registration_gain,
    short_widths,
)
from d2turb.sim.params import Optics, as_optics, r0_cn2_theta0
from d2turb.sim.tilt import differential_tilt_covariance, dr0_from_tilt_variance, tilt_variance_px2

# the terms of an interval other than the parameters a user can give, by the names :func:`narrowing` reports
TERMS = ("tiles", "clip", "texture", "footprint_below", "large_tilt_lower")


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
            dr0[:, qi] = dr0_from_tilt_variance(np.maximum(sig2, 0.0), 1.0, float(q), 1.0)
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
class ErrorBudget:
    """The log-sds of the interval per node: ``tiles`` and ``footprint_below`` (F,), ``clip`` and
    ``large_tilt_lower`` (F, Q; the last widens the lower bound only), ``extra`` (named scalars, e.g. texture)."""

    tiles: np.ndarray
    footprint_below: np.ndarray
    clip: np.ndarray
    large_tilt_lower: np.ndarray
    extra: dict

    def bounds(self, dr0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The 90 % bounds (lo, hi) of D/r0 (F, Q) per node."""
        other = sum(v * v for v in self.extra.values())
        both = np.sqrt(self.tiles[:, None] ** 2 + self.footprint_below[:, None] ** 2 + self.clip**2 + other)
        return dr0 * np.exp(-Z90 * np.sqrt(both**2 + self.large_tilt_lower**2)), dr0 * np.exp(Z90 * both)

    def at(self, fi: int, qi: int) -> dict:
        """The named log-sds at one node (measure.json's ``dr0_log_sd``)."""
        return {
            "tiles": float(self.tiles[fi]),
            "clip": float(self.clip[fi, qi]),
            "footprint_below": float(self.footprint_below[fi]),
            "large_tilt_lower": float(self.large_tilt_lower[fi, qi]),  # the lower bound's only
            **self.extra,
        }


def error_budget(dr0, grid: PriorGrid, tiles_sd, t_len: int, extra: dict) -> ErrorBudget:
    """The interval's terms at the nodes' estimates ``dr0`` (F, Q): the tile bootstrap, the calibrated clip term, the
    widening below the calibrated footprint and beyond the calibrated tilt, and ``extra``."""
    tilt_rms = np.sqrt(tilt_variance_px2(dr0, 1.0, grid.q[None, :], 1.0))  # per node: λ/(D·ifov) = q px
    return ErrorBudget(
        tiles=tiles_sd,
        footprint_below=EXTRAPOLATION_LOG_SD * np.log(np.maximum(GAIN_FOOTPRINT_PX[0] / grid.fs, 1.0)),
        clip=np.vectorize(lambda x: clip_log_sd(x, t_len))(dr0),
        large_tilt_lower=LARGE_TILT_LOG_SD * np.log(np.maximum(tilt_rms / CALIBRATED_TILT_RMS_PX, 1.0)),
        extra=dict(extra),
    )


def blur_allowed(blur: dict | None, grid: PriorGrid, dr0) -> tuple[np.ndarray, bool]:
    """The nodes (F, Q) whose optical blur q·s(D/r0) the fused frame's ``blur`` (its 90 % ``sigma_ci``) allows, and
    whether the blur was used (a confident estimate that allows some prior node); else every node."""
    allowed = np.ones(dr0.shape, bool)
    if blur is None or not blur.get("confident") or not blur["sigma_ci"][1] > 0:
        return allowed, False
    optical = grid.q[None, :] * short_widths(dr0)
    ok = (BLUR_GAIN[0] * optical <= blur["sigma_ci"][1]) & (
        BLUR_GAIN[1] * BLUR_EXCESS_MAX * optical >= blur["sigma_ci"][0]
    )
    if not ok[: grid.n_prior].any():
        return allowed, False
    return ok, True


@dataclass(frozen=True)
class Choice:
    """The point estimate's node (``fi``, ``qi``), the prior nodes the interval is the union of (``sel``, F × Q) and,
    with a given path, the given path's nodes it is intersected with (``gsel``, or None)."""

    fi: int
    qi: int
    sel: np.ndarray
    gsel: np.ndarray | None

    def union(self, low, high, point: float, sel=None, gsel=None) -> tuple[float, float]:
        """[min low, max high] over the selected nodes, intersected with the given path's nodes, holding ``point``."""
        sel = self.sel if sel is None else sel
        gsel = self.gsel if gsel is None else gsel
        env = (float(low[sel].min()), float(high[sel].max()))
        if gsel is not None:
            env = (max(float(low[gsel].min()), env[0]), min(float(high[gsel].max()), env[1]))
        return min(env[0], point), max(env[1], point)


def choose_point(grid: PriorGrid, resid, allowed) -> Choice:
    """The λ/(D·ifov) choice: without a path, the footprint that fits best (residual ``resid`` (F,)) among those the
    blur allows, with a path its node per q; then the allowed q in the middle (geometric) of the allowed range."""
    n_f, n_q = allowed.shape
    if not grid.path_given:
        cand = [fi for fi in range(grid.n_prior) if allowed[fi].any()]
        point_rows = [min(cand, key=lambda fi: resid[fi])] * n_q
    else:
        point_rows = list(range(grid.n_prior, n_f))  # footprint of the given path for q = grid.q[qi]
    q_ok = [qi for qi in range(n_q) if allowed[point_rows[qi], qi]] or list(range(n_q))
    q_mid = float(np.sqrt(grid.q[q_ok[0]] * grid.q[q_ok[-1]]))
    qi = min(q_ok, key=lambda k: abs(math.log(grid.q[k] / q_mid)))
    sel = np.zeros((n_f, n_q), bool)
    sel[: grid.n_prior] = allowed[: grid.n_prior]
    if not sel.any():
        sel[: grid.n_prior] = True
    gsel = None
    if grid.path_given:
        gsel = np.zeros((n_f, n_q), bool)
        gsel[point_rows, np.arange(n_q)] = True
        if (gsel & allowed).any():
            gsel &= allowed
    return Choice(point_rows[qi], qi, sel, gsel)


def narrowing(lo, hi, point: float, choice: Choice, optics: Optics, budget: ErrorBudget) -> dict:
    """What widens an interval (bounds ``lo``, ``hi`` per node, F × Q; ``point`` its estimate) most: its span, the
    parameter not given whose value narrows it most with the span the interval would have with it (``by``,
    ``span_with``: the union over the point's q column for ifov_rad, over its footprint row for path_length_m), or
    None when all were given, and the largest of the other terms (``widened_most_by``, one of ``TERMS``)."""
    lo_u, hi_u = choice.union(lo, hi, point)
    span = hi_u / lo_u if lo_u > 0 else math.inf
    with_ = {}
    if not optics.ifov_known:
        col = np.zeros_like(choice.sel)
        col[:, choice.qi] = True
        gcol = None if choice.gsel is None else (choice.gsel & col if (choice.gsel & col).any() else choice.gsel)
        with_["ifov_rad"] = choice.union(lo, hi, point, choice.sel & col if (choice.sel & col).any() else None, gcol)
    if optics.path_length_m is None:
        row = np.zeros_like(choice.sel)
        row[choice.fi] = True
        with_["path_length_m"] = choice.union(lo, hi, point, choice.sel & row if (choice.sel & row).any() else None)
    spans = {k: (b / a if a > 0 else math.inf) for k, (a, b) in with_.items()}
    by = min(spans, key=spans.get) if spans else None
    sd = budget.at(choice.fi, choice.qi)
    terms = {k: (1.0 if k == "large_tilt_lower" else 2.0) * sd.get(k, 0.0) for k in TERMS}
    return {
        "span": span,
        "by": by,
        "span_with": spans.get(by),
        "widened_most_by": max(terms, key=terms.get),
    }


def _dr0_widened_by(dr0, grid: PriorGrid, choice: Choice, budget: ErrorBudget, optics: Optics) -> str:
    """The term that widens D/r0's interval most, in words (measure.json's ``widened_by``): each term's share of
    ln(hi/lo) at the point's node, an unknown parameter's by the range of the nodes it spans."""
    sd = budget.at(choice.fi, choice.qi)
    spans = {
        "the tile bootstrap": 2 * Z90 * sd["tiles"],
        "the clip-to-clip scatter": 2 * Z90 * sd["clip"],
        "little texture": 2 * Z90 * sd.get("texture", 0.0),
        "a footprint below the calibrated 4 px": 2 * Z90 * sd["footprint_below"],
        "a tilt beyond the calibrated 3 px rms (the registration errs high)": Z90 * sd["large_tilt_lower"],
    }
    if not optics.ifov_known:
        qs = grid.q[choice.sel.any(0)]
        spans["unknown λ/(D·ifov) (give --ifov RAD)"] = 1.2 * math.log(qs.max() / qs.min()) if len(qs) else 0
    if optics.path_length_m is None:
        rows = np.arange(grid.n_prior)[choice.sel[: grid.n_prior].any(1)]
        per_q = [np.log(dr0[rows, qi].max() / dr0[rows, qi].min()) for qi in range(len(grid.q)) if len(rows)]
        spans["unknown path length (give --path-length M)"] = float(max(per_q)) if per_q else 0.0
    return max(spans, key=spans.get)


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
    """What a clip's structure sums say (:func:`estimate_from_sums`); :meth:`to_dict` gives measure.json's keys.

    ``seeing_px`` = λ/(r0·ifov), the seeing angle in px, and ``dr0`` with their 90 % intervals; ``dr0_determined``:
    D/r0's interval within ``MAX_SPAN`` (or below ``NEGLIGIBLE_DR0``); ``r0_m``, ``cn2``, ``theta0_urad`` as the optics
    allow (None without ifov: r0 = λ/(ρ·ifov); Cn² and θ0 also need the path); ``narrowing``: per quantity, its span
    and what narrows it most (:func:`narrowing`)."""

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


def estimate_from_sums(
    num, pairs, series, optics: Optics, bootstrap=200, seed=0, cache=None, blur=None, extra=None
) -> StrengthEstimate:
    """The fit and the intervals from the structure sums of :func:`d2turb.clip.motion.lag_sums` (what
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
    cache = {} if cache is None else cache
    t_len = num.shape[-1]
    grid = PriorGrid.of(optics)
    key = (t_len, tuple(np.round(grid.fs, 9)))
    if key not in cache:
        cache[key] = structure_models(series, t_len, list(1.0 / grid.fs))
    models = cache[key]
    seps = [r for r, _, _ in series]
    dr0 = fit_grid(num, pairs, seps, t_len, models, grid)
    gains = grid.gains(seps, dr0[:, int(np.argmin(np.abs(np.log(grid.q / 2.0))))])  # at the central q
    budget = error_budget(
        dr0, grid, bootstrap_log_sd(num, pairs, t_len, models, gains, bootstrap, seed), t_len, extra or {}
    )
    lo, hi = budget.bounds(dr0)
    allowed, blur_used = blur_allowed(blur, grid, dr0)
    _, resid, best = fit_per_footprint(num.sum(0), pairs.sum(0), t_len, models, gains)
    choice = choose_point(grid, resid, allowed)
    estimate = float(dr0[choice.fi, choice.qi])
    q = float(grid.q[choice.qi])
    ci = choice.union(lo, hi, estimate)
    # the seeing angle in px, ρ = λ/(r0·ifov) = λ/(D·ifov)·D/r0: tilt (σ² ∝ q^(1/3) ρ^(5/3)) and blur (∝ ρ) both
    # measure it, so it varies as q^(-1/5) only over the λ/(D·ifov) prior where D/r0 varies as q^(-6/5)
    q_nodes = grid.q[None, :]
    seeing = q * estimate
    seeing_ci = choice.union(q_nodes * lo, q_nodes * hi, seeing)
    span = ci[1] / ci[0] if ci[0] > 0 else math.inf
    phys = r0_cn2_theta0(estimate, optics) if optics.ifov_known else {"r0_m": None, "cn2": None, "theta0_urad": None}
    return StrengthEstimate(
        seeing_px=seeing,
        seeing_px_ci=[float(seeing_ci[0]), float(seeing_ci[1])],
        dr0=estimate,
        dr0_ci=[float(ci[0]), float(ci[1])],
        dr0_determined=bool(span <= MAX_SPAN or ci[1] < NEGLIGIBLE_DR0),
        dr0_log_sd=budget.at(choice.fi, choice.qi),
        widened_by=_dr0_widened_by(dr0, grid, choice, budget, optics),
        narrowing={
            "seeing_px": narrowing(q_nodes * lo, q_nodes * hi, seeing, choice, optics, budget),
            "dr0": narrowing(lo, hi, estimate, choice, optics, budget),
        },
        parameters=_parameters(optics, grid, choice, blur_used),
        lambda_over_d_px=q,
        tilt_var_px2=float(0.1816 * q**2 * estimate ** (5 / 3)),
        fit=_fitted(optics, grid, choice, int(best[choice.fi]), models.shape[1:4]),
        blur=blur,
        **phys,
    )
