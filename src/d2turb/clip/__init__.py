"""d2turb.clip: restore and measure a clip of a static scene seen through turbulence (docs/clips.md, docs/measure.md).

One room for the multi-frame work, ground floor up: ``registration`` (global shift and dense flow onto a
reference), ``camera`` (the camera's motion, the canvas frames are registered on, each output's return to its
frame's pose), ``fusion`` (mean, robust, FBA, sharpest), ``deblur`` (the Wiener filter with the short-exposure OTF, the
tone guard),
``blur`` (the edge estimate of a fused frame's blur), ``blur_net`` (the learned estimate), ``blind`` (the
default blind deblur that uses them), ``pipeline`` (:class:`ClipRestorer`: the sliding
window), ``motion`` (the image motion a measurement reads) and ``strength`` (D/r0, r0, Cn² and θ0 from it,
:func:`measure_clip`). The commands ``restore --temporal`` and ``measure`` call it.
"""

from d2turb.clip.blind import BlindDeblur
from d2turb.clip.blur import BlurEstimate, GaussianDeblur, estimate_blur, ringing_index
from d2turb.clip.deblur import (
    BALANCE_AT_2,
    LAPLACIAN_BALANCE_AT_2,
    SHARPEST_DR0_SCALE,
    PhysicsDeblur,
    deblur_dr0,
    default_balance,
    fusion_prior,
    laplacian_power,
    prior_power,
    wiener_deconvolve,
    wiener_gain,
    wiener_padding,
)
from d2turb.clip.fusion import fourier_burst_accumulation, sharpest_fusion
from d2turb.clip.motion import flow_variance_px2, registration_dr0, registration_tilt_variance
from d2turb.clip.pipeline import DEFAULT_TEMPORAL, FUSIONS, ClipFrame, ClipRestorer, restore_clip, window_start
from d2turb.clip.registration import DenseFlow, global_shift_px, remap
from d2turb.clip.strength import Optics, measure_clip

__all__ = [
    "BALANCE_AT_2",
    "DEFAULT_TEMPORAL",
    "FUSIONS",
    "LAPLACIAN_BALANCE_AT_2",
    "SHARPEST_DR0_SCALE",
    "BlindDeblur",
    "BlurEstimate",
    "ClipFrame",
    "ClipRestorer",
    "DenseFlow",
    "GaussianDeblur",
    "Optics",
    "PhysicsDeblur",
    "deblur_dr0",
    "default_balance",
    "estimate_blur",
    "flow_variance_px2",
    "fusion_prior",
    "fourier_burst_accumulation",
    "global_shift_px",
    "laplacian_power",
    "measure_clip",
    "prior_power",
    "registration_dr0",
    "registration_tilt_variance",
    "remap",
    "restore_clip",
    "ringing_index",
    "sharpest_fusion",
    "window_start",
    "wiener_deconvolve",
    "wiener_gain",
    "wiener_padding",
]
