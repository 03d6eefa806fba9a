"""The physical turbulence parameters (SI units; :class:`TurbulenceParams` holds the imaging :class:`Optics` of
:mod:`d2turb.sim.optics`) with validation, strength bins and depth modulation."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from d2turb.defaults import DEFAULT_APERTURE_M, DEFAULT_PATH_LENGTH_M, DEFAULT_WAVELENGTH_M
from d2turb.errors import D2TurbError
from d2turb.sim.optics import SAMPLING, Optics, as_optics, nyquist_ifov, positive_finite  # noqa: F401 (their old home)

BINS = {"weak": (1.0, 2.25), "medium": (2.25, 3.75), "strong": (3.75, 5.0)}  # D/r0 strength bins (paper Sec. 4.1)
BINS_RULE = f"weak < {BINS['medium'][0]:g} ≤ medium ≤ {BINS['medium'][1]:g} < strong"  # dr0_bin, for labels
MODULATIONS = ("uniform", "linear", "linear_offset", "power", "power_offset")
GEOMETRIES = ("path", "layer")
MAX_DR0 = 10.0


def fried_r0_spherical(cn2: float, path_length_m: float, wavelength_m: float) -> float:
    """Spherical-wave Fried parameter for constant Cn²: r0 = (0.158625 k² Cn² L)^(-3/5) (docs/physics.md §3)."""
    k = 2 * math.pi / wavelength_m
    return (0.158625 * k * k * cn2 * path_length_m) ** (-3 / 5)


def cn2_spherical(r0_m: float, path_length_m: float, wavelength_m: float) -> float:
    """The constant Cn² (m^-2/3) whose spherical-wave Fried parameter is ``r0_m``: the inverse of
    :func:`fried_r0_spherical`, Cn² = r0^(-5/3) / (0.158625 k² L)."""
    k = 2 * math.pi / wavelength_m
    return r0_m ** (-5 / 3) / (0.158625 * k * k * path_length_m)


ISOPLANATIC_WEIGHTS = {  # ∫0^L w(z) dz / L^(8/3) of the θ0 path weighting, z from the aperture
    "plane": 3 / 8,  # w = z^(5/3): a source at infinity (Fried, JOSA 72, 1982)
    "spherical": math.gamma(8 / 3) ** 2 / math.gamma(16 / 3),  # w = z^(5/3)(1 − z/L)^(5/3): B(8/3, 8/3) = 0.05641
}


def isoplanatic_angle(cn2: float, path_length_m: float, wavelength_m: float, wave: str = "spherical") -> float:
    """Isoplanatic angle θ0 (rad) of a path of constant Cn²: [2.914 k² Cn² ∫0^L w(z) dz]^(−3/5).

    Args:
        cn2: refractive-index structure constant, m^-2/3.
        path_length_m: path length L, m.
        wavelength_m: wavelength λ (k = 2π/λ), m.
        wave: the path weighting w, a key of ``ISOPLANATIC_WEIGHTS``: ``"spherical"`` (a point of the scene seen
            from the aperture; d2turb measure) or ``"plane"`` (Fried's θ0 = 0.314 r0/L with the spherical-wave r0;
            the page's derived quantities).

    Returns:
        θ0 in radians.
    """
    if wave not in ISOPLANATIC_WEIGHTS:
        raise D2TurbError(f"unknown wave {wave!r}; choose one of {', '.join(ISOPLANATIC_WEIGHTS)}")
    k = 2 * math.pi / wavelength_m
    return (2.914 * k * k * cn2 * path_length_m ** (8 / 3) * ISOPLANATIC_WEIGHTS[wave]) ** (-3 / 5)


_OPTICS_ARGS = ("aperture_m", "wavelength_m", "path_length_m", "ifov_rad")  # the flat keywords of the optics


@dataclass(init=False)
class TurbulenceParams:
    """Imaging and turbulence parameters: the :class:`Optics` (:attr:`optics`) and the turbulence on its path.

    ``dr0`` (D/r0 at the reference wavelength) or ``cn2`` (m^-2/3, constant along the path) sets the
    strength; with neither, D/r0 = 3. The optics are given as ``optics=Optics(...)`` or by the flat keywords
    ``aperture_m``, ``wavelength_m``, ``path_length_m``, ``ifov_rad`` (not both), which stay readable and settable
    as attributes: ``wavelength_m`` is one value or one per RGB channel, the reference wavelength (D/r0, default
    ifov) the middle one; ``ifov_rad`` defaults to Nyquist sampling λ_ref/(2D), and counts as given
    (``optics.ifov_known``); ``path_length_m`` to d2turb.defaults'. ``offset_s`` is the baseline offset s of Eq. 1.

    Args:
        aperture_m: aperture diameter D (m); default d2turb.defaults'.
        wavelength_m: wavelength (m), one value or three (R, G, B); default d2turb.defaults'.
        path_length_m: path length L (m); default d2turb.defaults'.
        dr0: turbulence strength D/r0 at the reference wavelength (give it or ``cn2``).
        cn2: refractive-index structure constant Cn² (m^-2/3), constant along the path.
        ifov_rad: angular size of a pixel (rad); default Nyquist λ_ref/(2D).
        n_zernike: Zernike modes simulated (Noll indices 2..n_zernike).
        offset_s: baseline offset s of the depth modulation (Eq. 1).
        modulation: the depth modulation M's form (``d2turb.sim.MODULATIONS``).
        tilt_geometry: "path" (constant Cn² along the path) or "layer" (one thin layer).
        layer_z_frac: the layer's distance from the aperture / L (``tilt_geometry="layer"``).
        psf_grid_px: spacing of the exact-PSF grid (px).
        optics: the optics as one :class:`Optics` (instead of the four flat keywords); its ifov, if not known, is
            Nyquist, its path length, if None, the default.

    Raises:
        D2TurbError: a value out of its range, or dr0 and cn2 that disagree (one line, naming the parameter).

    Example:
        >>> TurbulenceParams(dr0=2.0, wavelength_m=(630e-9, 525e-9, 450e-9)).reference_wavelength
        5.25e-07
    """

    optics: Optics
    dr0: float | None = None
    cn2: float | None = None
    n_zernike: int = 36
    offset_s: float = 0.5
    modulation: str = "power_offset"
    tilt_geometry: str = "path"  # "path": constant Cn² along the path; "layer": one thin layer
    layer_z_frac: float = 0.5  # layer distance from the aperture / L (tilt_geometry="layer")
    psf_grid_px: int = 16  # spacing of the exact-PSF grid in pixels

    def __init__(
        self,
        aperture_m: float | None = None,
        wavelength_m: float | tuple | None = None,
        path_length_m: float | None = None,
        dr0: float | None = None,
        cn2: float | None = None,
        ifov_rad: float | None = None,
        n_zernike: int = 36,
        offset_s: float = 0.5,
        modulation: str = "power_offset",
        tilt_geometry: str = "path",
        layer_z_frac: float = 0.5,
        psf_grid_px: int = 16,
        *,
        optics: Optics | None = None,
    ):
        flat = {"aperture_m": aperture_m, "wavelength_m": wavelength_m, "path_length_m": path_length_m}
        flat = {k: v for k, v in {**flat, "ifov_rad": ifov_rad}.items() if v is not None}
        if optics is None:
            defaults = {"aperture_m": DEFAULT_APERTURE_M, "wavelength_m": DEFAULT_WAVELENGTH_M}
            optics = _simulated_optics(**{**defaults, "path_length_m": DEFAULT_PATH_LENGTH_M, **flat})
        elif not isinstance(optics, Optics):
            raise D2TurbError(f"optics must be an Optics, got {type(optics).__name__}")
        elif flat:
            given = ", ".join(flat)
            raise D2TurbError(f"give the optics as optics= or as {', '.join(_OPTICS_ARGS)}, not both ({given})")
        elif optics.path_length_m is None or not optics.ifov_known:
            optics = _simulated_optics(
                optics.aperture_m,
                optics.wavelengths if optics.channels_m else optics.wavelength_m,
                optics.path_length_m or DEFAULT_PATH_LENGTH_M,
                optics.ifov_rad if optics.ifov_known else None,
            )
        self.optics, self.dr0, self.cn2, self.n_zernike = optics, dr0, cn2, n_zernike
        self.offset_s, self.modulation, self.tilt_geometry = offset_s, modulation, tilt_geometry
        self.layer_z_frac, self.psf_grid_px = layer_z_frac, psf_grid_px
        self._check()

    def _check(self):
        if self.cn2 is not None:
            cn2 = positive_finite("cn2", self.cn2)
            dr0_from_cn2 = self.aperture_m / fried_r0_spherical(cn2, self.path_length_m, self.reference_wavelength)
            if self.dr0 is not None and abs(float(self.dr0) - dr0_from_cn2) > 1e-3 * dr0_from_cn2:
                raise D2TurbError(
                    f"give either dr0 or cn2: dr0={self.dr0} disagrees with cn2={self.cn2} (D/r0={dr0_from_cn2:.4g})"
                )
            self.cn2, self.dr0 = cn2, dr0_from_cn2
        self.dr0 = 3.0 if self.dr0 is None else positive_finite("dr0", self.dr0)
        if self.dr0 > MAX_DR0:
            raise D2TurbError(f"D/r0 = {self.dr0:.3g} is beyond the supported range (0, {MAX_DR0:g}]")
        self.optics.check_sampling()
        if not isinstance(self.n_zernike, int) or not 4 <= self.n_zernike <= 120:
            raise D2TurbError(f"n_zernike must be an integer in [4, 120], got {self.n_zernike!r}")
        s = float(self.offset_s)
        if not math.isfinite(s) or not 0.0 <= s <= 1.0:
            raise D2TurbError(f"offset_s must be in [0, 1], got {self.offset_s!r}")
        self.offset_s = s
        if self.modulation not in MODULATIONS:
            raise D2TurbError(f"unknown modulation {self.modulation!r}; choose one of {', '.join(MODULATIONS)}")
        if self.tilt_geometry not in GEOMETRIES:
            raise D2TurbError(f"unknown tilt_geometry {self.tilt_geometry!r}; choose 'path' or 'layer'")
        if not 0.0 < float(self.layer_z_frac) < 1.0:
            raise D2TurbError(f"layer_z_frac must be in (0, 1), got {self.layer_z_frac!r}")
        if not isinstance(self.psf_grid_px, int) or self.psf_grid_px < 2:
            raise D2TurbError(f"psf_grid_px must be an integer >= 2, got {self.psf_grid_px!r}")

    # the optics' values under their flat names, readable and settable (a set replaces the optics, checked again)
    aperture_m = property(lambda self: self.optics.aperture_m, lambda self, v: self._set_optics(aperture_m=v))
    path_length_m = property(lambda self: self.optics.path_length_m, lambda self, v: self._set_optics(path_length_m=v))
    ifov_rad = property(lambda self: self.optics.ifov_rad, lambda self, v: self._set_optics(ifov_rad=v))

    @property
    def wavelength_m(self) -> float | tuple:
        """The wavelength (m), or the three of an RGB simulation (the flat keyword's value)."""
        return self.optics.channels_m or self.optics.wavelength_m

    @wavelength_m.setter
    def wavelength_m(self, value) -> None:
        self._set_optics(wavelength_m=value)

    def _set_optics(self, **change) -> None:
        o = self.optics
        now = {"aperture_m": o.aperture_m, "wavelength_m": self.wavelength_m, "path_length_m": o.path_length_m}
        self.optics = _simulated_optics(**{**now, "ifov_rad": o.ifov_rad, **change})

    @property
    def wavelengths(self) -> tuple:
        return self.optics.wavelengths

    @property
    def reference_wavelength(self) -> float:
        return self.optics.reference_wavelength

    @property
    def r0_m(self) -> float:
        return self.aperture_m / self.dr0

    @property
    def lambda_over_d_px(self) -> float:
        """λ/(D·ifov) at the reference wavelength: the diffraction angle in pixels (2 = Nyquist sampling)."""
        return self.optics.lambda_over_d_px

    def to_dict(self) -> dict:
        """The flat record of the dataset metadata (dataset.json, meta lines, NAME_meta.json): the keywords (the
        optics flat, three wavelengths as a list), then r0_m and reference_wavelength_m."""
        d = {"aperture_m": self.aperture_m, "wavelength_m": self.wavelength_m, "path_length_m": self.path_length_m}
        d.update(dr0=self.dr0, cn2=self.cn2, ifov_rad=self.ifov_rad)
        d.update({k: getattr(self, k) for k in ("n_zernike", "offset_s", "modulation", "tilt_geometry")})
        d.update(layer_z_frac=self.layer_z_frac, psf_grid_px=self.psf_grid_px)
        if isinstance(d["wavelength_m"], tuple):
            d["wavelength_m"] = list(d["wavelength_m"])
        d["r0_m"] = self.r0_m
        d["reference_wavelength_m"] = self.reference_wavelength
        return d


def _simulated_optics(aperture_m, wavelength_m, path_length_m, ifov_rad=None) -> Optics:
    """The :class:`Optics` of a simulation: the path length given, the ifov given or Nyquist at the reference
    wavelength, counted as given (``ifov_known``)."""
    aperture_m = positive_finite("aperture_m", aperture_m)  # the order of the checks before there was an Optics
    path_length_m = positive_finite("path_length_m", path_length_m)
    optics = Optics(aperture_m=aperture_m, wavelength_m=wavelength_m, ifov_rad=ifov_rad, path_length_m=path_length_m)
    return optics if optics.ifov_known else replace(optics, ifov_rad=optics.ifov_rad)


def make_params(
    aperture_m: float = DEFAULT_APERTURE_M,
    wavelength_m=DEFAULT_WAVELENGTH_M,
    path_length_m: float = DEFAULT_PATH_LENGTH_M,
    *,
    dr0: float | None = None,
    cn2: float | None = None,
    ifov_rad: float | None = None,
    offset_s: float = 0.5,
    modulation: str = "power_offset",
) -> TurbulenceParams:
    """The :class:`TurbulenceParams` of the physical options that ``d2turb simulate``, ``simulate-video`` and ``demo``
    share (their defaults are these; the page's Simulate tab gives the same optics as an :class:`Optics`).

    Args:
        wavelength_m: one wavelength, or a sequence of one or three (R G B), m.
        dr0, cn2: the strength (at most one; neither: D/r0 = 3).
        Others: the :class:`TurbulenceParams` fields of the same names.

    Raises:
        D2TurbError: not one or three wavelengths, or a value the parameters refuse (one line).
    """
    wl = list(wavelength_m) if isinstance(wavelength_m, (list, tuple)) else [wavelength_m]
    if len(wl) not in (1, 3):
        raise D2TurbError(f"wavelength_m takes one or three values, got {len(wl)}", param="wavelength_m")
    return TurbulenceParams(
        aperture_m=aperture_m,
        wavelength_m=tuple(wl) if len(wl) == 3 else wl[0],
        path_length_m=path_length_m,
        dr0=dr0,
        cn2=cn2,
        ifov_rad=ifov_rad,
        offset_s=offset_s,
        modulation=modulation,
    )


def dr0_bin(x: float) -> str:
    """Strength bin of D/r0 (paper Sec. 4.1): weak < 2.25 ≤ medium ≤ 3.75 < strong, from BINS (docs/physics.md §5)."""
    x = float(x)
    if not math.isfinite(x) or x <= 0:
        raise D2TurbError(f"D/r0 must be positive and finite, got {x!r}")
    return "weak" if x < BINS["medium"][0] else ("medium" if x <= BINS["medium"][1] else "strong")


def bin_spans(bins) -> list[tuple[float, float]]:
    """The D/r0 ranges of named bins, e.g. ``bin_spans(("weak", "strong"))``."""
    bins = tuple(bins)
    unknown = [b for b in bins if b not in BINS]
    if not bins or unknown or len(set(bins)) != len(bins):
        what = f"unknown bin {unknown[0]!r}" if unknown else f"bins must be distinct and non-empty, got {bins}"
        raise D2TurbError(f"{what}; choose from {','.join(BINS)}")
    return [BINS[b] for b in bins]


def dr0_from_uniform(u, spans) -> np.ndarray:
    """Map u in [0, 1) to D/r0 uniform over the union of ``spans`` [(low, high), ...] (float64 array).

    The one definition of D/r0 sampling: callers draw u from their own generator (numpy or torch)."""
    lo = np.array([a for a, _ in spans], dtype=np.float64)
    width = np.array([b - a for a, b in spans], dtype=np.float64)
    edges = np.cumsum(width)
    t = np.asarray(u, dtype=np.float64) * edges[-1]
    k = np.minimum(np.searchsorted(edges, t, side="left"), len(spans) - 1)
    return lo[k] + t - (edges[k] - width[k])


def sample_dr0(
    n: int, low: float | None = None, high: float | None = None, generator: torch.Generator | None = None, bins=None
) -> torch.Tensor:
    """n values of D/r0 uniform in [low, high], or over the union of ``bins`` (float32, CPU)."""
    if bins is not None:
        spans = bin_spans(bins)
    else:
        low, high = positive_finite("dr0 low", low), positive_finite("dr0 high", high)
        if high < low:
            raise D2TurbError(f"dr0 range is empty: low={low} > high={high}")
        if high > MAX_DR0:
            raise D2TurbError(f"dr0 high = {high} is beyond the supported range (0, {MAX_DR0:g}]")
        spans = [(low, high)]
    u = torch.rand(int(n), generator=generator, dtype=torch.float64)
    return torch.from_numpy(dr0_from_uniform(u.numpy(), spans)).float()


def depth_modulation(
    depth: torch.Tensor | None, strategy: str = "power_offset", offset_s: float = 0.5
) -> torch.Tensor | None:
    """Turbulence modulation M from relative depth d̃ in [0, 1] (far = 1).

    power_offset: z = L((1-s)d̃ + s) (Eq. 1), M = (z/L)^(3/5) (Eq. 3, z_max = L).
    Ablations: uniform M = 1 (P2S), linear M = d̃, linear_offset M = (1-s)d̃ + s, power M = d̃^(3/5).
    """
    if depth is None:
        return None
    if strategy not in MODULATIONS:
        raise D2TurbError(f"unknown modulation {strategy!r}; choose one of {', '.join(MODULATIONS)}")
    if not isinstance(depth, torch.Tensor) or not depth.is_floating_point():
        raise D2TurbError("depth must be a floating torch.Tensor")
    if not torch.isfinite(depth).all():
        raise D2TurbError("depth contains NaN or infinite values")
    if depth.numel() and (depth.min() < -1e-6 or depth.max() > 1 + 1e-6):
        raise D2TurbError(f"depth must lie in [0, 1] (far = 1), got [{depth.min():.3g}, {depth.max():.3g}]")
    d = depth.clamp(0, 1)
    s = float(offset_s)
    if strategy == "uniform":
        return torch.ones_like(d)
    if strategy == "linear":
        return d
    z_frac = (1 - s) * d + s  # Eq. 1 divided by L
    if strategy == "linear_offset":
        return z_frac
    if strategy == "power":
        return d.clamp_min(1e-12).pow(0.6) * (d > 0)
    return z_frac.clamp_min(1e-12).pow(0.6) * (z_frac > 0)  # Eq. 3


def r0_cn2_theta0(dr0: float, optics: Optics) -> dict:
    """r0 = D/(D/r0); with L: the constant-path Cn² from the spherical-wave r0 = (0.158625 k² Cn² L)^(−3/5)
    (docs/physics.md §3) and θ0 = (2.914 k² Cn² L^(8/3) B(8/3, 8/3))^(−3/5) (spherical wave, constant Cn²)."""
    out = {"r0_m": optics.aperture_m / dr0 if dr0 > 0 else math.inf, "cn2": None, "theta0_urad": None}
    if optics.path_length_m is None or not dr0 > 0:
        return out
    cn2 = cn2_spherical(out["r0_m"], optics.path_length_m, optics.wavelength_m)
    theta0 = isoplanatic_angle(cn2, optics.path_length_m, optics.wavelength_m, wave="spherical")
    out.update(cn2=cn2, theta0_urad=theta0 * 1e6)
    return out
