"""Weights I/O. ``save_pretrained`` writes one .safetensors file whose metadata holds the model config
(``d2turb_config``: JSON of ``model.config``) and ``d2turb_sha256``: a SHA-256 over the tensors (name, dtype, shape,
bytes, in name order). ``load_pretrained`` rebuilds the model, verifies the checksum and loads strictly."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import torch
from torch import nn

from d2turb.errors import D2TurbError
from d2turb.io import atomic_path
from d2turb.models.registry import create_model

CONFIG_KEY, CHECKSUM_KEY = "d2turb_config", "d2turb_sha256"


def tensors_sha256(tensors: dict[str, torch.Tensor]) -> str:
    digest = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name].detach().cpu().contiguous()
        digest.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        digest.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


def save_pretrained(model: nn.Module, path: str | os.PathLike) -> Path:
    """Write ``model``'s weights and config to ``path`` (.safetensors), atomically."""
    from safetensors.torch import save_file

    path = Path(path)
    if path.suffix != ".safetensors":
        raise D2TurbError(f"{path}: weights file must end in .safetensors")
    config = getattr(model, "config", None)
    if not isinstance(config, dict) or "name" not in config:
        raise D2TurbError("save_pretrained: model has no .config (build it with d2turb.models.create_model)")
    tensors = {k: v.detach().cpu().contiguous().clone() for k, v in model.state_dict().items()}
    metadata = {CONFIG_KEY: json.dumps(config), CHECKSUM_KEY: tensors_sha256(tensors), "format": "pt"}
    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata=metadata)
    return path


def load_pretrained(path: str | os.PathLike, device="cpu") -> nn.Module:
    """Rebuild the model saved by :func:`save_pretrained`, verify its checksum, load strictly; returns it in eval
    mode."""
    from safetensors import safe_open

    path = Path(path)
    if not path.is_file():
        raise D2TurbError(f"{path}: weights file not found")
    try:
        with safe_open(str(path), framework="pt") as f:
            metadata = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as exc:  # safetensors raises its own error types for truncated / garbage files
        raise D2TurbError(f"{path}: corrupt weights file ({exc.__class__.__name__})") from None
    if CONFIG_KEY not in metadata or CHECKSUM_KEY not in metadata:
        raise D2TurbError(f"{path}: not a d2turb weights file (no config or checksum in its metadata)")
    if tensors_sha256(tensors) != metadata[CHECKSUM_KEY]:
        raise D2TurbError(f"{path}: checksum mismatch, the weights file is corrupt or was modified")
    try:
        config = dict(json.loads(metadata[CONFIG_KEY]))
        name = config.pop("name")
    except (ValueError, KeyError, TypeError):
        raise D2TurbError(f"{path}: unreadable model config in its metadata") from None
    model = create_model(name, **config)
    try:
        model.load_state_dict(tensors, strict=True)
    except RuntimeError as exc:
        raise D2TurbError(f"{path}: weights do not match model {name!r} ({str(exc).splitlines()[0]})") from None
    return model.to(device).eval()
