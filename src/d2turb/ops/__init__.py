from d2turb.ops.warp import Warp, warp

__all__ = ["Warp", "warp"]
