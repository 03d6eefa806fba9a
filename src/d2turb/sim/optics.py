"""The imaging optics (:class:`Optics`): one type for the simulator (:attr:`TurbulenceParams.optics
<d2turb.sim.TurbulenceParams.optics>`, the PSFs of :class:`~d2turb.sim.psf.PupilPSF`, the geometry banks),
``d2turb measure``, the clip deblur and the page, with one definition of each quantity derived from it (λ/D in
pixels, the Nyquist pixel, the tilt footprint)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from d2turb.defaults import DEFAULT_APERTURE_M, DEFAULT_WAVELENGTH_M
from d2turb.errors import D2TurbError

SAMPLING = (0.25, 16.0)  # pixel size ifov over the Nyquist pixel λ/(2D): the range the simulator supports


def positive_finite(name: str, value) -> float:
    """``value`` as a float, or one-line ``D2TurbError`` naming ``name`` unless it is finite and > 0."""
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise D2TurbError(f"{name} must be a number, got {value!r}") from exc
    if not math.isfinite(v) or v <= 0:
        raise D2TurbError(f"{name} must be positive and finite, got {value!r}")
    return v


def nyquist_ifov(wavelength_m: float, aperture_m: float) -> float:
    """The Nyquist pixel angle λ/(2D) (rad): the default ifov everywhere."""
    return wavelength_m / (2 * aperture_m)


@dataclass(frozen=True)
class Optics:
    """The imaging optics; defaults from :mod:`d2turb.defaults`.

    Args:
        aperture_m: aperture diameter D (m).
        wavelength_m: wavelength λ (m), one value or three (R, G, B); of three, the attribute is their reference
            (middle) wavelength, and :attr:`channels_m` holds the three.
        ifov_rad: angular size of a pixel (rad); None: not known, taken as Nyquist λ/(2D) (``ifov_known`` False:
            the measurement then marginalises λ/(D·ifov)).
        path_length_m: path length L (m); None: not known (no Cn², θ0; the tilt's correlation scale is fitted).
        fps: frame rate (optional; only to express a measured wind in m/s).
        channels_m: the three wavelengths (R, G, B) of an RGB simulation, ``wavelength_m`` their middle one; None:
            one channel, ``wavelength_m``. Set by ``wavelength_m=(R, G, B)``; given, it must agree with it.

    Raises:
        D2TurbError: a value that is not positive and finite, not one or three wavelengths, or λ ≥ D (one line,
            naming it).

    Example:
        >>> Optics(wavelength_m=(630e-9, 525e-9, 450e-9)).wavelength_m
        5.25e-07
    """

    aperture_m: float = DEFAULT_APERTURE_M
    wavelength_m: float = DEFAULT_WAVELENGTH_M
    ifov_rad: float | None = None
    path_length_m: float | None = None
    fps: float | None = None
    channels_m: tuple[float, float, float] | None = None
    ifov_known: bool = field(init=False, default=False)  # ifov_rad was given (else Nyquist, and marginalised)

    def __post_init__(self):
        set_ = object.__setattr__
        set_(self, "ifov_known", self.ifov_rad is not None)
        set_(self, "aperture_m", positive_finite("aperture_m", self.aperture_m))
        wl = self.wavelength_m
        wl = tuple(wl) if isinstance(wl, (list, tuple)) else (wl,)
        if len(wl) not in (1, 3):
            raise D2TurbError(f"wavelength_m must be one value or three (R, G, B), got {len(wl)}")
        wl = tuple(positive_finite("wavelength_m", w) for w in wl)
        channels = self.channels_m
        if channels is not None:
            channels = tuple(positive_finite("channels_m", w) for w in channels)
            if len(channels) != 3 or (len(wl) == 3 and wl != channels) or (len(wl) == 1 and wl[0] != channels[1]):
                raise D2TurbError(f"channels_m {channels} must be three wavelengths with wavelength_m {wl} the middle")
        set_(self, "channels_m", wl if len(wl) == 3 else channels)
        set_(self, "wavelength_m", wl[len(wl) // 2])
        for name in ("ifov_rad", "path_length_m", "fps"):
            value = getattr(self, name)
            if value is not None:
                set_(self, name, positive_finite(name, value))
        if max(self.wavelengths) >= self.aperture_m:
            raise D2TurbError(
                f"wavelength {max(self.wavelengths)} m is not smaller than the aperture {self.aperture_m} m"
            )
        if self.ifov_rad is None:
            set_(self, "ifov_rad", nyquist_ifov(self.wavelength_m, self.aperture_m))

    @classmethod
    def from_footprint(
        cls, footprint_px: float, lambda_over_d_px: float, path_length_m: float, wavelength_m: float
    ) -> Optics:
        """The optics whose tilt footprint :attr:`footprint_px` = D/(ifov·L) and :attr:`lambda_over_d_px`
        q = λ/(D·ifov) are given: D = sqrt(footprint·λ·L/q) (footprint = qD²/(λL)), ifov = λ/(qD)."""
        aperture = math.sqrt(footprint_px * wavelength_m * path_length_m / lambda_over_d_px)
        ifov = wavelength_m / (lambda_over_d_px * aperture)
        return cls(aperture_m=aperture, wavelength_m=wavelength_m, ifov_rad=ifov, path_length_m=path_length_m)

    @property
    def wavelengths(self) -> tuple:
        """The simulated channels' wavelengths: :attr:`channels_m`, or (``wavelength_m``,)."""
        return self.channels_m if self.channels_m is not None else (self.wavelength_m,)

    @property
    def reference_wavelength(self) -> float:
        """The wavelength D/r0, the phase and the default ifov refer to (of three channels the middle one)."""
        return self.wavelength_m

    @property
    def lambda_over_d_px(self) -> float:
        """λ/(D·ifov) at the reference wavelength: the diffraction angle in pixels (2 = Nyquist sampling)."""
        return self.wavelength_m / (self.aperture_m * self.ifov_rad)

    @property
    def footprint_px(self) -> float:
        """The aperture's footprint at the target in pixels, D/(ifov·L): the tilt field's correlation scale."""
        if self.path_length_m is None:
            raise D2TurbError("the tilt footprint D/(ifov·L) needs the path length")
        return self.aperture_m / (self.ifov_rad * self.path_length_m)

    def check_sampling(self) -> None:
        """The pixel must be within SAMPLING × of the Nyquist pixel λ/(2D) at every wavelength: the pupil grid (a
        box of ~32·ifov·2D/λ samples across, per channel), and the PSF window (~(2.5·D/r0 + 3)·λ/(D·ifov) px),
        grow with its inverse and with it; outside, the optics would ask for gigabytes to terabytes before any
        image is touched (``--ifov 1`` asked for a petabyte). Checked before anything is allocated."""
        lo, hi = SAMPLING
        nyquist = [nyquist_ifov(w, self.aperture_m) for w in self.wavelengths]
        ratio = [self.ifov_rad / n for n in nyquist]
        if min(ratio) < lo or max(ratio) > hi:
            raise D2TurbError(
                f"ifov_rad = {self.ifov_rad:.3g} rad is {min(ratio) if min(ratio) < lo else max(ratio):.3g}× "
                f"the Nyquist pixel λ/(2D); the simulator supports {lo:g}× to {hi:g}×: ifov_rad from "
                f"{lo * max(nyquist):.3g} to {hi * min(nyquist):.3g} rad for this aperture and wavelength "
                f"(docs/cli.md, physical parameters)",
                param="ifov_rad",
            )


OPTICS_KEYS = ("aperture_m", "wavelength_m", "ifov_rad", "path_length_m", "fps")  # what a user gives (as_optics)


def as_optics(optics) -> Optics:
    """An :class:`Optics` from itself, None (defaults), a dict of its fields, or anything that holds one as
    ``.optics`` (a :class:`~d2turb.sim.TurbulenceParams`)."""
    if isinstance(optics, Optics):
        return optics
    if optics is None or isinstance(optics, dict):
        unknown = sorted(set(optics or {}) - set(OPTICS_KEYS))
        if unknown:
            raise D2TurbError(f"unknown optics {unknown}; choose from {', '.join(OPTICS_KEYS)}")
        return Optics(**(optics or {}))
    if isinstance(getattr(optics, "optics", None), Optics):
        return optics.optics
    raise D2TurbError(f"optics must be an Optics, a dict or TurbulenceParams, got {type(optics).__name__}")
