"""d2turb.clip: restore and measure a clip of a static scene seen through turbulence (docs/clips.md, docs/measure.md).

One room for the multi-frame work, ground floor up (docs/architecture.md draws it): ``registration`` (global shift
and dense flow onto a reference), ``camera`` (the camera's motion, the canvas frames are registered on, each output's
return to its frame's pose), ``frames`` (a restored frame, a held frame, the windows), ``fba`` and ``sharpest`` (two
fusion algorithms) and ``fusion`` (the registry of fusions by name: mean, robust, fba, sharpest), ``deblur`` (what a
deblur provides; the Wiener filter with the short-exposure OTF; the tone guard), ``blur`` (the edge estimate of a fused
frame's blur), ``blur_net`` (the learned estimate), ``blind`` (the default blind deblur that uses them); then the
restorer: ``state`` (one clip's state), ``stages`` (a registration round, an output), ``schedule`` (what runs when, in
which thread) and ``pipeline`` (:class:`ClipRestorer`, which composes them); ``motion`` (the image motion a
measurement reads) and ``strength`` (D/r0, r0, Cn² and θ0 from it, :func:`measure_clip`). The commands
``restore --temporal`` and ``measure`` call it.
"""

from d2turb.clip.blind import BlindDeblur
from d2turb.clip.blur import BlurEstimate, GaussianDeblur, estimate_blur, ringing_index
from d2turb.clip.deblur import (
    BALANCE_AT_2,
    LAPLACIAN_BALANCE_AT_2,
    ClipDeblur,
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
from d2turb.clip.fba import fourier_burst_accumulation
from d2turb.clip.frames import ClipFrame, window_start
from d2turb.clip.fusion import SHARPEST_DR0_SCALE, Fusion, make_fusion, register_fusion
from d2turb.clip.motion import flow_variance_px2, registration_dr0, registration_tilt_variance
from d2turb.clip.pipeline import DEFAULT_TEMPORAL, FUSIONS, ClipRestorer, restore_clip
from d2turb.clip.registration import DenseFlow, global_shift_px, remap
from d2turb.clip.sharpest import sharpest_fusion
from d2turb.clip.strength import Optics, measure_clip

__all__ = [
    "BALANCE_AT_2",
    "DEFAULT_TEMPORAL",
    "FUSIONS",
    "LAPLACIAN_BALANCE_AT_2",
    "SHARPEST_DR0_SCALE",
    "BlindDeblur",
    "BlurEstimate",
    "ClipDeblur",
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
    "Fusion",
    "fusion_prior",
    "fourier_burst_accumulation",
    "global_shift_px",
    "laplacian_power",
    "make_fusion",
    "measure_clip",
    "prior_power",
    "register_fusion",
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
