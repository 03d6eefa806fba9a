"""Imaging geometries for training and test data: which apertures, ranges, pixels and depth offsets to simulate.

What one frame shows of the tilt is set by two numbers in pixels (docs/physics.md): the tilt amplitude
σ ≈ 0.426·q·(D/r0)^(5/6) per axis, with q = λ/(D·ifov) pixels per λ/D (q = 2 at Nyquist), and the correlation
scale, the aperture's footprint at mid-path D/(ifov·L): two pixels this far apart see tilts from air volumes
that barely overlap. With the simulator's default optics (d2turb.defaults; L = 1 km, Nyquist) the footprint is 38 px, so
a 256² crop moves almost as one piece and the learnable part of the flow is small.

A :class:`GeometryDistribution` draws L log-uniformly in ``range_m`` and the footprint log-uniformly in
``footprint_px``; the aperture follows from them at fixed q (D = sqrt(footprint·λ·L/q), :meth:`Optics.from_footprint
<d2turb.sim.Optics.from_footprint>`), and the depth offset s of Eq. 1 is uniform in ``offset_s``.
:meth:`GeometryDistribution.bank` stratifies ``size`` geometries over that box
(a Latin hypercube from a fixed seed), so a training run and the test set made from the same distribution see the
same geometries; D/r0 is drawn per sample on top of them (the strength bins).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np

from d2turb.defaults import DEFAULT_WAVELENGTH_M
from d2turb.errors import D2TurbError
from d2turb.sim.optics import Optics
from d2turb.sim.params import TurbulenceParams


@dataclass(frozen=True)
class GeometryDistribution:
    """Ranges of the imaging geometry; all lengths in metres, footprints in pixels (see the module docstring)."""

    range_m: tuple[float, float] = (1000.0, 10000.0)
    footprint_px: tuple[float, float] = (4.0, 32.0)
    offset_s: tuple[float, float] = (0.3, 0.9)
    samples_per_lambda_d: float = 2.0  # q; 2 = Nyquist (larger q makes the PSF window, and the simulator, slower)
    wavelength_m: float = DEFAULT_WAVELENGTH_M
    size: int = 16
    seed: int = 0
    # q drawn log-uniformly per geometry in this range (the blind test set); None: ``samples_per_lambda_d`` for all
    samples_per_lambda_d_range: tuple[float, float] | None = None

    def __post_init__(self):
        for name in ("range_m", "footprint_px", "offset_s"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
                raise D2TurbError(f"geometry {name} must be an increasing pair of positive numbers, got {(lo, hi)}")
        if self.offset_s[1] > 1:
            raise D2TurbError(f"geometry offset_s must lie in (0, 1], got {self.offset_s}")
        q_range = self.samples_per_lambda_d_range
        if q_range is not None and not (
            math.isfinite(q_range[0]) and math.isfinite(q_range[1]) and 0 < q_range[0] <= q_range[1]
        ):
            raise D2TurbError(f"geometry samples_per_lambda_d_range must be an increasing positive pair, got {q_range}")
        if self.size < 1:
            raise D2TurbError(f"geometry bank size must be at least 1, got {self.size}")

    def bank(self) -> list[TurbulenceParams]:
        """``size`` geometries, one per stratum of each parameter (Latin hypercube, fixed seed)."""
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 7]))
        n = self.size
        strata = [(rng.permutation(n) + rng.random(n)) / n for _ in range(3)]
        qs = [self.samples_per_lambda_d] * n
        if self.samples_per_lambda_d_range is not None:  # a 4th stratum, drawn after the others (field unchanged)
            qs = [_log_uniform(self.samples_per_lambda_d_range, u) for u in (rng.permutation(n) + rng.random(n)) / n]
        out = []
        for u_range, u_foot, u_s, q in zip(*strata, qs):
            length = _log_uniform(self.range_m, u_range)
            footprint = _log_uniform(self.footprint_px, u_foot)
            out.append(
                TurbulenceParams(
                    optics=Optics.from_footprint(footprint, q, length, self.wavelength_m),
                    offset_s=self.offset_s[0] + float(u_s) * (self.offset_s[1] - self.offset_s[0]),
                )
            )
        return out

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


def _log_uniform(span: tuple[float, float], u: float) -> float:
    lo, hi = span
    return float(math.exp(math.log(lo) + u * (math.log(hi) - math.log(lo))))


def footprint_px(params: TurbulenceParams) -> float:
    """The aperture's footprint at the target in pixels, D/(ifov·L): the tilt field's correlation scale
    (:attr:`Optics.footprint_px <d2turb.sim.Optics.footprint_px>` of ``params.optics``)."""
    return params.optics.footprint_px


GEOMETRIES: dict[str, GeometryDistribution | None] = {
    "fixed": None,  # one geometry: TurbulenceParams defaults plus the user's overrides
    "field": GeometryDistribution(),  # ranges 1-10 km, footprints 4-32 px: what real long-range footage shows
    # issue 35's blind test set: as field, and λ/(D·ifov) 1–4 px drawn per geometry (use --batch 1: one per clip)
    "blind": GeometryDistribution(samples_per_lambda_d_range=(1.0, 4.0), size=32, seed=35),
}


def geometry_bank(name: str, overrides: dict | None = None) -> list[TurbulenceParams]:
    """The geometries of a named distribution (``fixed``: one, from ``overrides``; others ignore overrides other
    than the strength model, which must then be left alone)."""
    if name not in GEOMETRIES:
        raise D2TurbError(f"unknown geometry {name!r}; choose from {', '.join(GEOMETRIES)}")
    overrides = dict(overrides or {})
    dist = GEOMETRIES[name]
    try:
        if dist is None:
            return [TurbulenceParams(**overrides)]
        clash = sorted(set(overrides) & {"aperture_m", "wavelength_m", "path_length_m", "ifov_rad", "offset_s"})
        if clash:
            raise D2TurbError(f"geometry {name!r} sets {', '.join(clash)} itself; use geometry 'fixed' to set them")
        strength = {"dr0": None} if "cn2" in overrides else {}  # the bank's resolved D/r0 would disagree with Cn²
        return [replace(p, **{**strength, **overrides}) for p in dist.bank()]
    except TypeError as exc:
        raise D2TurbError(f"bad simulator parameter: {exc}") from exc
