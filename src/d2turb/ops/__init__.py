from d2turb.ops.splat import BackwardFlow, backward_flow, splat
from d2turb.ops.warp import Warp, warp

__all__ = ["BackwardFlow", "Warp", "backward_flow", "splat", "warp"]
