from d2turb.ops.checks import check_image_tensor, check_shape
from d2turb.ops.splat import BackwardFlow, backward_flow, splat
from d2turb.ops.warp import Warp, sample_at, warp

__all__ = [
    "BackwardFlow",
    "Warp",
    "backward_flow",
    "check_image_tensor",
    "check_shape",
    "sample_at",
    "splat",
    "warp",
]
