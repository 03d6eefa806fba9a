"""Names of the models in the tables and grids of ``evaluate``: a weights file called like every run folder's
(``model.safetensors``, ``best``, ``last``, ``ema``) is named by the model of its config and its folder, e.g.
``d2turb_lite (lite-run)``, instead of a column "model" per run."""

from __future__ import annotations

import json
import os
from pathlib import Path

from d2turb.models.hub import IDENTITY_NAME
from d2turb.models.weights import CONFIG_KEY, WEIGHTS_SUFFIX

GENERIC_STEMS = {"model", "best", "last", "ema", "weights", "checkpoint"}  # the names a run folder gives its files


def config_model_name(path: Path) -> str | None:
    """The model name in a d2turb weights file's metadata (the header only is read), or None."""
    try:
        from safetensors import safe_open

        with safe_open(str(path), framework="pt") as f:
            metadata = f.metadata() or {}
        name = json.loads(metadata[CONFIG_KEY]).get("name")
    except Exception:  # any unreadable or foreign file: the loader reports it, the label falls back to the stem
        return None
    return name if isinstance(name, str) else None


def weights_label(weights: str | os.PathLike) -> str:
    """``input`` → ``input``; a weights name → itself; a file → its stem, or, for a generic stem (``model`` …),
    ``<config model name> (<folder>)`` (``<folder>/<stem>`` when the config cannot be read)."""
    text = os.fspath(weights)
    if text == IDENTITY_NAME:
        return text
    path = Path(text)
    if path.suffix.lower() != WEIGHTS_SUFFIX and "/" not in text and os.sep not in text:
        return text  # a weights name such as d2turb-nafnet
    if path.stem.lower() not in GENERIC_STEMS:
        return path.stem
    folder = path.resolve().parent.name if path.exists() else path.parent.name
    name = config_model_name(path) if path.is_file() else None
    if name is None:
        return f"{folder}/{path.stem}" if folder else path.stem
    return f"{name} ({folder})" if folder else name
