"""d2turb: physics-validated, depth-aware single-frame atmospheric turbulence toolkit (D²Turb)."""

__version__ = "0.1.0"

from d2turb.errors import D2TurbError  # noqa: E402

__all__ = ["D2TurbError", "__version__"]
