"""Relative depth providers (d̃ ∈ [0, 1], far = 1, tensors (1, H, W)): measured/precomputed maps,
a weight-free prior, and Depth Anything V2 from a local folder."""

from d2turb.depth.io import depth_for_image, load_depth, normalize_depth, resize_depth
from d2turb.depth.prior import DEFAULT_METHOD, METHODS, estimate_depth_prior, guided_filter


def __getattr__(name):  # lazy: transformers is heavy and optional
    if name == "DepthAnything":
        from d2turb.depth.anything import DepthAnything

        return DepthAnything
    raise AttributeError(name)


__all__ = [
    "DEFAULT_METHOD",
    "METHODS",
    "DepthAnything",
    "depth_for_image",
    "estimate_depth_prior",
    "guided_filter",
    "load_depth",
    "normalize_depth",
    "resize_depth",
]
