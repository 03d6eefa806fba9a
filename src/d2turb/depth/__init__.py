"""Relative depth providers (d̃ ∈ [0, 1], far = 1, tensors (1, H, W)): measured/precomputed maps,
a weight-free prior, and Depth Anything V2 from a local folder."""

from d2turb.depth.anything import DepthAnything  # imports transformers only when a model is loaded
from d2turb.depth.io import load_depth, normalize_depth, resize_depth
from d2turb.depth.prior import DEFAULT_METHOD, METHODS, estimate_depth_prior, guided_filter
from d2turb.depth.spec import check_depth_spec, depth_for_image

__all__ = [
    "DEFAULT_METHOD",
    "METHODS",
    "DepthAnything",
    "check_depth_spec",
    "depth_for_image",
    "estimate_depth_prior",
    "guided_filter",
    "load_depth",
    "normalize_depth",
    "resize_depth",
]
