"""The page's controls as plain values: what each tab accepts (:class:`Limits`), the Simulate tab's settings
(:class:`SimSettings`) checked and converted to SI units (:class:`SimValues`), the built-in samples and the weights
the Restore tab lists. Every problem a user can cause is a one-line :class:`d2turb.errors.D2TurbError`."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import torch

from d2turb.data.samples import SAMPLES, sample_images
from d2turb.defaults import DEFAULT_APERTURE_M, DEFAULT_DR0, DEFAULT_PATH_LENGTH_M, DEFAULT_WAVELENGTH_M
from d2turb.errors import D2TurbError
from d2turb.models.hub import (
    IDENTITY_NAME,
    RECOMMENDED_WEIGHTS,
    resolve_weights,
    shipped_weights_dir,
    weights_search_path,
)
from d2turb.models.weights import WEIGHTS_SUFFIX
from d2turb.sim import MODULATIONS, Optics, TurbulenceParams

STRENGTHS = ("D/r0", "Cn²")
DEPTH_SOURCES = ("none", "prior", "upload")
IMAGE_SOURCES = ("sample", "upload")


@dataclass(frozen=True)
class Limits:
    """What the app accepts (a local app on a laptop: the simulator's memory grows with the image area)."""

    sim_pixels: int = 1 << 21  # 2.1 MP: 1920x1080 fits
    restore_pixels: int = 25_000_000  # 6000x4000 fits; restore is tiled, ~14 float32 per pixel besides the model
    video_frames: int = 150


# ---- small helpers ---------------------------------------------------------------------------------------------
def safe_stem(name: str, default: str = "image") -> str:
    """A file stem that is safe on a command line and cannot be read as an option (no leading '-')."""
    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", Path(str(name)).stem).strip("._")[:64]
    if not stem:
        return default
    return stem if stem[0].isalnum() else f"{default}_{stem}"


def fmt_float(x: float) -> str:
    """Shortest text that parses back to the same float (``repr``), so a command line is exact."""
    return repr(float(x))


def _number(name: str, value, positive: bool = True) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise D2TurbError(f"{name} must be a number, got {value!r}") from exc
    if not math.isfinite(v) or (positive and v <= 0):
        raise D2TurbError(f"{name} must be {'positive and ' if positive else ''}finite, got {value!r}")
    return float(f"{v:.12g}")  # drops the browser's float noise (a slider's 3.0500000000000003 → 3.05)


def _scaled(name: str, text, exponent: int) -> float:
    """A number typed in a unit (nm: exponent -9, µrad: -6) → SI through its decimal text, so that "525" nm is
    exactly the float of ``525e-9`` (the CLI's default and what a typed ``--wavelength 525e-9`` gives)."""
    m = re.fullmatch(r"([0-9.]+)(?:e([-+]?[0-9]+))?", repr(_number(name, text)))  # a positive finite float's repr
    return float(f"{m[1]}e{int(m[2] or 0) + exponent}")


def parse_wavelengths_nm(text) -> list[float]:
    """'525' or '620 530 460' (nm; commas allowed) → wavelengths in metres."""
    tokens = [t for t in re.split(r"[\s,;]+", str(text or "").strip()) if t]
    if len(tokens) not in (1, 3):
        raise D2TurbError(f"wavelength: give one value or three (R G B) in nm, got {text!r}")
    return [_scaled("wavelength (nm)", t, -9) for t in tokens]


def known(suffixes) -> str:
    """File suffixes as one line for a message."""
    return " ".join(sorted(suffixes))


def check_pixels(name: str, width: int, height: int, limit: int) -> None:
    if width * height > limit:
        raise D2TurbError(
            f"{name}: {width}x{height} is too large for the app ({width * height / 1e6:.1f} MP > "
            f"{limit / 1e6:.1f} MP); use the command line, which has no limit"
        )


def whole(name: str, value, at_least: int | None = None, unit: str = "pixels") -> int:
    """A whole number typed in the page (gradio gives floats) → int; one-line error otherwise."""
    if not float(value).is_integer() or (at_least is not None and value < at_least):
        floor = f" >= {at_least}" if at_least is not None else ""
        raise D2TurbError(f"{name} must be a whole number of {unit}{floor}, got {value}")
    return int(value)


# ---- simulate --------------------------------------------------------------------------------------------------
@dataclass
class SimSettings:
    """The Simulate tab's controls. Units as shown in the page: wavelength nm, IFOV µrad (0 or None = Nyquist)."""

    source: str = "sample"
    sample: str = "astronaut"
    upload: str | None = None
    strength: str = "D/r0"
    dr0: float = DEFAULT_DR0
    cn2: float = 1e-14
    aperture_m: float = DEFAULT_APERTURE_M
    wavelength_nm: str = f"{DEFAULT_WAVELENGTH_M * 1e9:g}"  # "525": parsed back to exactly DEFAULT_WAVELENGTH_M
    path_length_m: float = DEFAULT_PATH_LENGTH_M
    ifov_urad: float | None = None
    depth: str = "none"
    depth_upload: str | None = None
    disparity: bool = False
    modulation: str = "power_offset"
    offset_s: float = 0.5
    seed: int = 0


@lru_cache(maxsize=1)
def _samples() -> dict:
    return sample_images()


def sample_image(name: str) -> torch.Tensor:
    """A built-in sample (3, 192, 256) in [0, 1]: the demo's images (``SAMPLES``)."""
    if name not in SAMPLES:
        raise D2TurbError(f"unknown sample {name!r}; choose one of {', '.join(SAMPLES)}")
    return _samples()[name]


@dataclass(frozen=True)
class SimValues:
    """The checked values of one Simulate run, in SI units: its ``d2turb simulate`` argument list is written from
    these (:func:`d2turb.app.jobs.simulate_argv`), and :meth:`params` checks them before the command runs.
    ``depth``: none, prior or the depth file's name in the run folder; ``optics``: the page's optics (its ifov not
    known where the page leaves it at Nyquist)."""

    seed: int
    dr0: float | None
    cn2: float | None
    depth: str
    disparity: bool
    optics: Optics
    modulation: str
    offset_s: float

    def params(self):
        """The simulator's :class:`~d2turb.sim.TurbulenceParams` (one-line D2TurbError for impossible values)."""
        return TurbulenceParams(
            optics=self.optics, dr0=self.dr0, cn2=self.cn2, offset_s=self.offset_s, modulation=self.modulation
        )


def sim_values(s: SimSettings, depth_name: str | None) -> SimValues:
    """The page's settings checked and converted (nm, µrad → m, rad), each problem a one-line D2TurbError."""
    seed = _number("seed", s.seed, positive=False)
    if not (seed.is_integer() and 0 <= seed < 2**63):
        raise D2TurbError(f"seed must be a whole number in [0, 2^63), got {s.seed!r}")
    if s.strength == "D/r0":
        dr0, cn2 = _number("D/r0", s.dr0), None
    elif s.strength == "Cn²":
        dr0, cn2 = None, _number("Cn²", s.cn2)
    else:
        raise D2TurbError(f"strength must be one of {', '.join(STRENGTHS)}, got {s.strength!r}")
    if s.depth == "upload":
        if not depth_name:
            raise D2TurbError("depth source 'upload': upload a depth map first")
        depth, disparity = depth_name, bool(s.disparity)
    elif s.depth in ("none", "prior"):
        depth, disparity = s.depth, False
    else:
        raise D2TurbError(f"depth source must be one of {', '.join(DEPTH_SOURCES)}, got {s.depth!r}")
    aperture = _number("aperture", s.aperture_m)
    wavelengths = parse_wavelengths_nm(s.wavelength_nm)
    path_length = _number("path length", s.path_length_m)
    ifov = None if s.ifov_urad in (None, "", 0, 0.0) else _scaled("pixel IFOV (µrad)", s.ifov_urad, -6)
    optics = Optics(aperture_m=aperture, wavelength_m=wavelengths, ifov_rad=ifov, path_length_m=path_length)
    if s.modulation not in MODULATIONS:
        raise D2TurbError(f"modulation must be one of {', '.join(MODULATIONS)}, got {s.modulation!r}")
    offset = _number("offset s", s.offset_s, positive=False)
    return SimValues(int(seed), dr0, cn2, depth, disparity, optics, s.modulation, offset)


# ---- restore ---------------------------------------------------------------------------------------------------
def weights_choices() -> list[tuple[str, Path | None]]:
    """(name, file) of every weights name ``resolve_weights`` finds in its folders (in its order: the first folder
    holding a name wins), after the identity baseline ``("input", None)``."""
    found: dict[str, Path] = {}
    for folder in dict.fromkeys(p.parent for p in weights_search_path("x")):
        for f in sorted(folder.glob(f"*{WEIGHTS_SUFFIX}")) if folder.is_dir() else []:
            if f.stem in found or f.stem == IDENTITY_NAME:
                continue
            try:
                if resolve_weights(f.stem) == f:
                    found[f.stem] = f
            except D2TurbError:  # not a valid name (e.g. a space in it): only usable as a path
                continue
    return [(IDENTITY_NAME, None), *found.items()]


def default_weights(choices: list[tuple[str, Path | None]]) -> str:
    """The weights preselected in the page: the recommended shipped one (``RECOMMENDED_WEIGHTS``), else the first
    shipped one, else the first found, else "input"."""
    found = [(name, path) for name, path in choices if path is not None]
    shipped = [name for name, path in found if path.parent == shipped_weights_dir()]
    shipped.sort(key=lambda name: name != RECOMMENDED_WEIGHTS)
    return (shipped or [name for name, _ in found] or [choices[0][0]])[0]
