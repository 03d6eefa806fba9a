"""Name → constructor registries for complete models and for deblurring backbones.

``create_model(name, **cfg)`` builds a model and records ``model.config = {"name": name, **cfg}`` so
:func:`d2turb.models.weights.save_pretrained` can rebuild it. Adding a backbone is a one-file job: decorate
its class with ``@register_backbone("name")`` (and import the file in ``d2turb/models/__init__.py``).
"""

from __future__ import annotations

import json
from collections.abc import Callable

from torch import nn

from d2turb.errors import D2TurbError

_MODELS: dict[str, Callable[..., nn.Module]] = {}
_BACKBONES: dict[str, Callable[..., nn.Module]] = {}
_STANDALONE: dict[str, Callable[..., nn.Module]] = {}  # "wrapper": factory(backbone_name, **cfg) -> a model


def _register(table: dict, kind: str, name: str):
    def deco(factory):
        if name in table:
            raise ValueError(f"{kind} {name!r} is already registered")
        table[name] = factory
        return factory

    return deco


def register_model(name: str):
    """Decorator: register a complete model (forward(image) -> dict with deblurred/restored/bwd_flow_px/guide)."""
    return _register(_MODELS, "model", name)


def register_backbone(name: str):
    """Decorator: register a deblurring backbone (forward(image) -> (image_out, F_guide), attr ``guide_channels``)."""
    return _register(_BACKBONES, "backbone", name)


def register_standalone(factory):
    """Decorator: the wrapper that makes a registered backbone a complete model, ``factory(backbone_name, **cfg)``;
    :func:`create_model` uses it for a backbone name (the registry itself knows no concrete model)."""
    _register(_STANDALONE, "standalone wrapper", "wrapper")(factory)
    return factory


def list_models() -> list[str]:
    """Complete models, plus every backbone as a standalone restorer (restored = backbone output)."""
    return sorted(set(_MODELS) | set(_BACKBONES))


def list_backbones() -> list[str]:
    return sorted(_BACKBONES)


def _build(table: dict, kind: str, name: str, cfg: dict) -> nn.Module:
    if name not in table:
        raise D2TurbError(f"unknown {kind} {name!r}; available: {', '.join(sorted(table))}")
    try:
        json.dumps(cfg)
    except TypeError as exc:
        raise D2TurbError(f"{kind} {name!r}: config must be JSON-serialisable ({exc})") from exc
    return _construct(kind, name, table[name], cfg)


# What a constructor raises for a config it cannot build: an unknown / missing keyword, inconsistent values, and
# what torch raises while allocating layers of impossible sizes (a negative width; 64 levels overflow the size).
BUILD_ERRORS = (TypeError, ValueError, RuntimeError, ArithmeticError, IndexError, KeyError)


def _construct(kind: str, name: str, factory: Callable[..., nn.Module], cfg: dict, *args) -> nn.Module:
    try:
        return factory(*args, **cfg)
    except BUILD_ERRORS as exc:
        if isinstance(exc, D2TurbError):
            raise
        first = (str(exc).strip().splitlines() or [exc.__class__.__name__])[0]
        raise D2TurbError(f"{kind} {name!r}: bad config {json.dumps(cfg)[:300]} ({first})") from exc


def create_backbone(name: str, **cfg) -> nn.Module:
    model = _build(_BACKBONES, "backbone", name, cfg)
    model.config = {"name": name, **cfg}
    return model


def create_model(name: str, **cfg) -> nn.Module:
    """Build a registered model, e.g. ``create_model("d2turb", backbone="restormer", injection="aspi")``; a backbone
    name gives that backbone as a standalone restorer, configured by the backbone's own keywords."""
    if name not in _MODELS and name not in _BACKBONES:
        raise D2TurbError(f"unknown model {name!r}; available: {', '.join(list_models())}")
    if name not in _MODELS:
        try:
            json.dumps(cfg)
        except TypeError as exc:
            raise D2TurbError(f"model {name!r}: config must be JSON-serialisable ({exc})") from exc
        model = _construct("model", name, _STANDALONE["wrapper"], cfg, name)
    else:
        model = _build(_MODELS, "model", name, cfg)
    model.config = {"name": name, **cfg}
    return model
