from d2turb.ops.checks import check_image_tensor, check_shape
from d2turb.ops.splat import BackwardFlow, InvertFlow, backward_flow, invert_flow, splat
from d2turb.ops.warp import Warp, sample_at, warp

__all__ = [
    "BackwardFlow",
    "InvertFlow",
    "Warp",
    "backward_flow",
    "check_image_tensor",
    "check_shape",
    "invert_flow",
    "sample_at",
    "splat",
    "warp",
]
