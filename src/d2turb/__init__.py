"""d2turb: physics-validated, depth-aware single-frame atmospheric turbulence toolkit (D²Turb)."""

__version__ = "0.1.0"

from d2turb.errors import D2TurbError  # noqa: E402

__all__ = ["D2TurbError", "Restorer", "Simulator", "TurbulenceParams", "__version__"]

_LAZY = {"Restorer": "d2turb.restore", "Simulator": "d2turb.sim", "TurbulenceParams": "d2turb.sim"}


def __getattr__(name):  # lazy, so `import d2turb` (and the CLI's --help) stays fast
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'd2turb' has no attribute {name!r}")
