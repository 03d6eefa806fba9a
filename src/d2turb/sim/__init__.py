"""Physics-validated, depth-aware atmospheric turbulence simulator (paper Eq. 1–7)."""

from d2turb.sim.derived import derived_quantities
from d2turb.sim.optics import Optics, as_optics
from d2turb.sim.params import (
    BINS,
    MODULATIONS,
    TurbulenceParams,
    bin_spans,
    cn2_spherical,
    depth_modulation,
    dr0_bin,
    dr0_from_uniform,
    fried_r0_spherical,
    isoplanatic_angle,
    make_params,
    sample_dr0,
)
from d2turb.sim.sequence import FrozenFlow
from d2turb.sim.simulator import SimResult, Simulator, simulate

__all__ = [
    "BINS",
    "MODULATIONS",
    "Optics",
    "TurbulenceParams",
    "as_optics",
    "Simulator",
    "SimResult",
    "FrozenFlow",
    "simulate",
    "sample_dr0",
    "dr0_bin",
    "dr0_from_uniform",
    "bin_spans",
    "depth_modulation",
    "fried_r0_spherical",
    "cn2_spherical",
    "isoplanatic_angle",
    "make_params",
    "derived_quantities",
]
