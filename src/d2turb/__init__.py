"""d2turb: physics-validated, depth-aware single-frame atmospheric turbulence toolkit (D²Turb).

What a user needs, from the top (docs/api.md): :class:`Simulator` and :class:`TurbulenceParams` (simulate),
:class:`Restorer` (restore one image), :class:`ClipRestorer` and :func:`measure_clip` (restore and measure a clip),
:class:`BlindDeblur` and :class:`PhysicsDeblur` (the deblurring of a clip's fused frames)."""

__version__ = "0.1.0"

from d2turb.errors import D2TurbError  # noqa: E402

__all__ = [
    "BlindDeblur",
    "ClipRestorer",
    "D2TurbError",
    "PhysicsDeblur",
    "Restorer",
    "Simulator",
    "TurbulenceParams",
    "__version__",
    "measure_clip",
]

_LAZY = {
    "Simulator": "d2turb.sim",
    "TurbulenceParams": "d2turb.sim",
    "Restorer": "d2turb.restore",
    "ClipRestorer": "d2turb.clip",
    "measure_clip": "d2turb.clip",
    "BlindDeblur": "d2turb.clip",
    "PhysicsDeblur": "d2turb.clip",
}


def __getattr__(name):  # lazy, so `import d2turb` (and the CLI's --help) stays fast
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'd2turb' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
