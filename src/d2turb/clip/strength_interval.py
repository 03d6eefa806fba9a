"""The interval step of the strength inversion (``d2turb.clip.strength_fit.estimate_from_sums``, after the fit):
from the fitted D/r0 per node of the prior grid to the point estimate and its 90 % intervals (docs/measure.md).

Its steps, each a function: the interval's error budget per node (:func:`error_budget`: the tile bootstrap, the
calibrated clip term, the widening below the calibrated footprint and beyond the calibrated tilt), the λ/(D·ifov)
nodes the fused frame's blur allows (:func:`blur_allowed`), the point and the nodes the interval is the union of
(:func:`choose_point`), and what widens each interval most (:func:`narrowing`). :func:`interval_of` runs them and
returns one :class:`Interval`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from d2turb.clip.strength_calib import (
    BLUR_EXCESS_MAX,
    BLUR_GAIN,
    CALIBRATED_TILT_RMS_PX,
    CLIP_FRAMES,
    CLIP_LOG_SD,
    CLIP_WINDOW_VAR,
    EXTRAPOLATION_LOG_SD,
    GAIN_DR0,
    GAIN_FOOTPRINT_PX,
    LARGE_TILT_LOG_SD,
    Z90,
)
from d2turb.sim.otf import short_exposure_width
from d2turb.sim.params import Optics

if TYPE_CHECKING:
    from d2turb.clip.strength_fit import Fit, PriorGrid

# the terms of an interval other than the parameters a user can give, by the names :func:`narrowing` reports
TERMS = ("tiles", "clip", "texture", "footprint_below", "large_tilt_lower")


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


def clip_log_sd(dr0: float, frames: int = CLIP_FRAMES) -> float:
    """The interval's clip-to-clip term (sd of ln D/r0) at strength ``dr0`` from ``CLIP_LOG_SD``, for a clip or window
    of ``frames`` frames: variance CLIP_LOG_SD² + CLIP_WINDOW_VAR·(CLIP_FRAMES/frames − 1), not below its value at
    CLIP_FRAMES (longer clips keep the calibrated term)."""
    var = float(np.interp(dr0, GAIN_DR0, CLIP_LOG_SD)) ** 2
    return math.sqrt(var + CLIP_WINDOW_VAR * max(CLIP_FRAMES / int(frames) - 1.0, 0.0))


def error_budget(fit: Fit, extra: dict) -> ErrorBudget:
    """The interval's terms at the nodes' estimates ``fit.dr0`` (F, Q): the tile bootstrap, the calibrated clip term,
    the widening below the calibrated footprint and beyond the calibrated tilt, and ``extra``."""
    tilt_rms = np.sqrt(fit.tilt_var_px2)
    return ErrorBudget(
        tiles=fit.tiles_sd,
        footprint_below=EXTRAPOLATION_LOG_SD * np.log(np.maximum(GAIN_FOOTPRINT_PX[0] / fit.grid.fs, 1.0)),
        clip=np.vectorize(lambda x: clip_log_sd(x, fit.t_len))(fit.dr0),
        large_tilt_lower=LARGE_TILT_LOG_SD * np.log(np.maximum(tilt_rms / CALIBRATED_TILT_RMS_PX, 1.0)),
        extra=dict(extra),
    )


def short_widths(dr0: np.ndarray) -> np.ndarray:
    """The Gaussian-equivalent width s(D/r0) of the tilt-removed OTF in λ/D (``sim.otf.short_exposure_width``),
    interpolated on 40 nodes from 0.05 to 20 (clamped outside)."""
    nodes = np.geomspace(0.05, 20.0, 40)
    table = np.array([short_exposure_width(x) for x in nodes])
    return np.interp(np.clip(dr0, nodes[0], nodes[-1]), nodes, table)


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


@dataclass(frozen=True)
class Interval:
    """The point estimate and its 90 % intervals (:func:`interval_of`): D/r0 ``dr0`` at the point's node
    (``choice``) and λ/(D·ifov) ``lambda_over_d_px`` there, the seeing angle ``seeing_px`` = λ/(D·ifov)·D/r0, their
    intervals, the named log-sds at the point (``log_sd``), the term that widens D/r0's most (``widened_by``), what
    narrows each most (``narrowing``), and whether the fused frame's blur narrowed the nodes (``blur_used``)."""

    choice: Choice
    dr0: float
    dr0_ci: tuple[float, float]
    lambda_over_d_px: float
    seeing_px: float
    seeing_px_ci: tuple[float, float]
    log_sd: dict
    widened_by: str
    narrowing: dict
    blur_used: bool


def interval_of(fit: Fit, optics: Optics, blur: dict | None, extra: dict) -> Interval:
    """The :class:`Interval` of a :class:`~d2turb.clip.strength_fit.Fit`: its error budget (with the named extra
    log-sds ``extra``), the nodes the fused frame's ``blur`` allows, the point and the unions of the nodes' bounds."""
    grid, dr0 = fit.grid, fit.dr0
    budget = error_budget(fit, extra)
    lo, hi = budget.bounds(dr0)
    allowed, blur_used = blur_allowed(blur, grid, dr0)
    choice = choose_point(grid, fit.resid, allowed)
    estimate = float(dr0[choice.fi, choice.qi])
    q = float(grid.q[choice.qi])
    ci = choice.union(lo, hi, estimate)
    # the seeing angle in px, ρ = λ/(r0·ifov) = λ/(D·ifov)·D/r0: tilt (σ² ∝ q^(1/3) ρ^(5/3)) and blur (∝ ρ) both
    # measure it, so it varies as q^(-1/5) only over the λ/(D·ifov) prior where D/r0 varies as q^(-6/5)
    q_nodes = grid.q[None, :]
    seeing = q * estimate
    seeing_ci = choice.union(q_nodes * lo, q_nodes * hi, seeing)
    return Interval(
        choice=choice,
        dr0=estimate,
        dr0_ci=ci,
        lambda_over_d_px=q,
        seeing_px=seeing,
        seeing_px_ci=seeing_ci,
        log_sd=budget.at(choice.fi, choice.qi),
        widened_by=_dr0_widened_by(dr0, grid, choice, budget, optics),
        narrowing={
            "seeing_px": narrowing(q_nodes * lo, q_nodes * hi, seeing, choice, optics, budget),
            "dr0": narrowing(lo, hi, estimate, choice, optics, budget),
        },
        blur_used=blur_used,
    )
