"""Weights I/O. ``save_pretrained`` writes one .safetensors file whose metadata holds the model config
(``d2turb_config``: JSON of ``model.config``) and ``d2turb_sha256``: a SHA-256 over the tensors (name, dtype, shape,
bytes, in name order). ``load_pretrained`` rebuilds the model, verifies the checksum and loads strictly.

It also reads the authors' checkpoints (HertzDot222/D2Turb): a ``.pth``/``.pt``/``.ckpt``/``.bin`` file (read with
``torch.load(weights_only=True)``) or a plain ``.safetensors`` file holding a state dict, possibly nested under
``params_ema``, ``params``, ``state_dict`` or ``model`` and with ``module.`` prefixes; its keys are renamed by
:func:`~d2turb.models.convert.convert_official_state_dict`. Every load is strict (missing, unexpected and mis-shaped
keys are listed in one :class:`~d2turb.errors.D2TurbError`, nothing is loaded) and refuses non-finite (NaN/Inf)
weights. Where a weights *name* is looked for: :mod:`d2turb.models.hub`."""

from __future__ import annotations

import hashlib
import json
import math
import os
from pathlib import Path

import torch
from torch import nn

from d2turb.errors import D2TurbError
from d2turb.io import atomic_path
from d2turb.models.convert import convert_official_state_dict, is_official_layout, legacy_config, official_key
from d2turb.models.registry import create_model

PICKLE_SUFFIXES = (".pth", ".pt", ".ckpt", ".bin")


NESTING_KEYS = ("params_ema", "params", "state_dict", "model")  # in order of preference


CONFIG_KEY, CHECKSUM_KEY, FORMAT_KEY = "d2turb_config", "d2turb_sha256", "d2turb_format"


WEIGHTS_SUFFIX = ".safetensors"


FORMAT = "2"  # 2: the authors' architecture is the default; files without the key are format 1


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
    metadata = {
        CONFIG_KEY: json.dumps(config),
        CHECKSUM_KEY: tensors_sha256(tensors),
        FORMAT_KEY: FORMAT,
        "format": "pt",
    }
    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata=metadata)
    return path


def _unwrap(obj, path: Path, key: str | None) -> dict:
    """The state dict inside a checkpoint: nested under ``key`` or one of NESTING_KEYS, ``module.`` prefixes
    stripped."""
    if key is not None and not (isinstance(obj, dict) and isinstance(obj.get(key), dict)):
        keys = ", ".join(map(str, list(obj)[:10])) if isinstance(obj, dict) else type(obj).__name__
        raise D2TurbError(f"{path}: no state dict found under {key!r} (top-level keys: {keys or 'none'})")
    while isinstance(obj, dict) and not (obj and all(isinstance(v, torch.Tensor) for v in obj.values())):
        found = [k for k in ([key] if key else NESTING_KEYS) if k in obj and isinstance(obj[k], dict)]
        if not found:
            keys = ", ".join(map(str, list(obj)[:10])) or "none"
            want = repr(key) if key else " / ".join(NESTING_KEYS)
            raise D2TurbError(f"{path}: no state dict found under {want} (top-level keys: {keys})")
        obj, key = obj[found[0]], None
    if not isinstance(obj, dict):
        raise D2TurbError(f"{path}: not a state dict (found {type(obj).__name__})")
    out = {}
    for k, v in obj.items():
        k = str(k)
        while k.startswith("module."):
            k = k[len("module.") :]
        out[k] = v
    return out


def read_state_dict(path: str | os.PathLike, key: str | None = None) -> dict[str, torch.Tensor]:
    """A state dict from a ``.safetensors`` file (metadata ignored) or a ``.pth``/``.pt``/``.ckpt``/``.bin`` file
    (``torch.load(weights_only=True)``, on CPU), unwrapped from ``key`` (default: the first of ``params_ema``,
    ``params``, ``state_dict``, ``model`` present) with ``module.`` prefixes stripped."""
    path = Path(path)
    if not path.is_file():
        raise D2TurbError(f"{path}: weights file not found")
    suffix = path.suffix.lower()
    if suffix == ".safetensors":
        return _unwrap(_read_safetensors(path)[0], path, None)
    if suffix not in PICKLE_SUFFIXES:
        raise D2TurbError(f"{path}: unknown weights format (use .safetensors or {', '.join(PICKLE_SUFFIXES)})")
    try:
        obj = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # unpickling refused (weights_only) or a corrupt archive
        first = (str(exc).strip().splitlines() or [""])[0]
        raise D2TurbError(f"{path}: cannot read checkpoint ({exc.__class__.__name__}: {first})") from exc
    return _unwrap(obj, path, key)


def _read_safetensors(path: Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    from safetensors import safe_open

    try:
        with open(path, "rb"):  # a file we may not read is no corrupt file (safetensors says FileNotFoundError)
            pass
    except OSError as exc:
        raise D2TurbError(f"{path}: cannot read weights file ({exc.strerror or exc.__class__.__name__})") from exc
    try:
        with safe_open(str(path), framework="pt") as f:
            metadata = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as exc:  # safetensors raises its own error types for truncated / garbage files
        raise D2TurbError(f"{path}: corrupt weights file ({exc.__class__.__name__})") from exc
    return tensors, metadata


def _listing(names: list[str], limit: int = 8) -> str:
    shown = ", ".join(names[:limit])
    return shown + (f" (and {len(names) - limit} more)" if len(names) > limit else "")


def _dtype_kind(dtype: torch.dtype) -> str:
    """bool, integer, floating or complex: a file's tensor must be of the model's kind (a float16 file loads into a
    float32 model; a bool or integer tensor never stands for weights)."""
    if dtype == torch.bool:
        return "bool"
    if dtype.is_complex:
        return "complex"
    return "floating" if dtype.is_floating_point else "integer"


def load_state_dict_strict(model: nn.Module, state_dict: dict, source: str, display=None) -> None:
    """Load ``state_dict`` into ``model`` only if its keys and shapes match exactly and every tensor is finite;
    otherwise raise one D2TurbError listing the missing, unexpected, mis-shaped or non-finite tensors (``display``
    maps our key names to the names shown, e.g. :func:`official_key`). Nothing is loaded on error."""
    display = display or (lambda k: k)
    expected = model.state_dict()
    bad_type = sorted(k for k, v in state_dict.items() if not isinstance(v, torch.Tensor))
    if bad_type:
        raise D2TurbError(f"{source}: entries that are not tensors: {_listing([display(k) for k in bad_type])}")
    name = getattr(model, "config", {}).get("name", type(model).__name__)
    if not set(expected) & set(state_dict):
        raise D2TurbError(
            f"{source}: not weights of model {name!r} (none of its {len(state_dict)} keys matches, e.g. "
            f"{_listing(sorted(state_dict), 3) or 'no keys'})"
        )
    missing = sorted(set(expected) - set(state_dict))
    unexpected = sorted(set(state_dict) - set(expected))
    shapes = sorted(
        f"{display(k)} {tuple(state_dict[k].shape)} vs {tuple(expected[k].shape)}"
        for k in set(expected) & set(state_dict)
        if state_dict[k].shape != expected[k].shape
    )
    problems = [
        f"{label}: {_listing(names)}"
        for label, names in (
            ("missing", [display(k) for k in missing]),
            ("unexpected", [display(k) for k in unexpected]),
            ("mis-shaped (file vs model)", shapes),
        )
        if names
    ]
    if problems:
        raise D2TurbError(f"{source}: weights do not match model {name!r}; " + "; ".join(problems))
    kinds = sorted(
        f"{display(k)} {state_dict[k].dtype} vs {expected[k].dtype}"
        for k in expected
        if _dtype_kind(state_dict[k].dtype) != _dtype_kind(expected[k].dtype)
    )
    if kinds:
        raise D2TurbError(f"{source}: tensors of the wrong type (file vs model): {_listing(kinds)}")
    nonfinite = sorted(
        display(k) for k, v in state_dict.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())
    )
    if nonfinite:
        raise D2TurbError(f"{source}: non-finite weights (NaN/Inf) in {_listing(nonfinite)}")
    if any(t.is_meta for t in expected.values()):
        # built on the meta device: adopt fresh copies (own, aligned storage; the model's dtypes)
        state_dict = {
            k: v.to(dtype=expected[k].dtype, memory_format=torch.contiguous_format, copy=True)
            for k, v in state_dict.items()
        }
        model.load_state_dict(state_dict, strict=True, assign=True)
    else:
        model.load_state_dict(state_dict, strict=True)


MAX_PARAMETERS = 4_000_000_000  # a config asking for more (16 GB of float32) is taken as damaged


def _build_for_loading(name: str, config: dict, source: Path) -> nn.Module:
    """The model on the meta device (no random initialisation: loading replaces every tensor), unless it has
    tensors outside its state dict (non-persistent buffers), which need a real initialisation. A config that
    cannot be built (an unknown model, a negative width, 64 levels) is a ``D2TurbError`` naming ``source``."""
    try:
        with torch.device("meta"):
            net = create_model(name, **config)
        size = sum(t.numel() for t in net.state_dict().values())
        if size > MAX_PARAMETERS:
            raise D2TurbError(f"model {name!r} of config {json.dumps(config)[:200]} would hold {size:,} values")
        if sum(1 for _ in net.parameters()) + sum(1 for _ in net.buffers()) != len(net.state_dict()):
            net = create_model(name, **config)
    except D2TurbError as exc:
        raise D2TurbError(f"{source}: cannot build its model: {exc}") from exc
    return net


def _verified_config(path: Path, tensors: dict, metadata: dict) -> dict:
    """The config of a ``save_pretrained`` file, once its checksum matches its tensors."""
    if CONFIG_KEY not in metadata or CHECKSUM_KEY not in metadata:
        raise D2TurbError(f"{path}: not a d2turb weights file (no config or checksum in its metadata)")
    if tensors_sha256(tensors) != metadata[CHECKSUM_KEY]:
        raise D2TurbError(f"{path}: checksum mismatch, the weights file is corrupt or was modified")
    try:
        config = dict(json.loads(metadata[CONFIG_KEY]))
        if not isinstance(config["name"], str):
            raise TypeError(config["name"])
    except (ValueError, KeyError, TypeError) as exc:
        raise D2TurbError(f"{path}: unreadable model config in its metadata") from exc
    return config


def read_verified(path: str | os.PathLike) -> tuple[dict[str, torch.Tensor], dict]:
    """(tensors, config) of a file written by :func:`save_pretrained`, its checksum verified; for networks outside
    the model registry (e.g. ``d2turb.clip.blur_net``), which build themselves from the config."""
    path = Path(path)
    if not path.is_file():
        raise D2TurbError(f"{path}: weights file not found")
    if path.suffix.lower() != ".safetensors":
        raise D2TurbError(f"{path}: weights file must end in .safetensors")
    tensors, metadata = _read_safetensors(path)
    return tensors, _verified_config(path, tensors, metadata)


def load_pretrained(
    path: str | os.PathLike,
    device="cpu",
    model: str = "d2turb",
    config: dict | None = None,
    key: str | None = None,
) -> nn.Module:
    """Load weights strictly and return the model in eval mode on ``device``.

    A file written by :func:`save_pretrained` rebuilds its own model from its metadata (checksum verified;
    ``model``/``config``/``key`` are ignored; files from before the authors' architecture became the default are
    rebuilt with their old defaults, see :func:`legacy_config`). Any other file (the authors' ``.pth`` or a plain
    ``.safetensors`` state dict, see :func:`read_state_dict`) is converted by :func:`convert_official_state_dict` and
    loaded into ``create_model(model, **config)``, by default the paper configuration of D²Turb.

    Raises:
        D2TurbError: missing/corrupt file, checksum mismatch, missing/unexpected/mis-shaped keys, NaN/Inf weights.
    """
    path = Path(path)
    if not path.is_file():
        raise D2TurbError(f"{path}: weights file not found")
    metadata = {}
    if path.suffix.lower() == ".safetensors":
        tensors, metadata = _read_safetensors(path)
    if CONFIG_KEY in metadata or CHECKSUM_KEY in metadata:
        config = _verified_config(path, tensors, metadata)
        name = config.pop("name")
        version = metadata.get(FORMAT_KEY, "1")
        if version not in ("1", FORMAT):
            raise D2TurbError(
                f"{path}: weights format {version!r} is not one this d2turb reads (1, {FORMAT}); "
                "a newer d2turb wrote it"
            )
        if version == "1":
            config = legacy_config(name, config)
        net = _build_for_loading(name, config, path)
        load_state_dict_strict(net, tensors, str(path))
    else:
        state = read_state_dict(path, key)
        official = is_official_layout(state)
        net = _build_for_loading(model, dict(config or {}), path)
        load_state_dict_strict(net, convert_official_state_dict(state), str(path), official_key if official else None)
    return net.to(device).eval()


def weights_info(path: str | os.PathLike) -> dict:
    """What a save_pretrained file holds, without loading it: ``{"model": registered name, "params": count,
    "bytes": file size}`` (``model`` None for a file without a d2turb config)."""
    from safetensors import safe_open

    path = Path(path)
    try:
        with safe_open(str(path), framework="pt") as f:
            metadata = f.metadata() or {}
            params = sum(math.prod(f.get_slice(k).get_shape()) for k in f.keys())
        model = json.loads(metadata[CONFIG_KEY])["name"] if CONFIG_KEY in metadata else None
    except Exception as exc:  # safetensors' own error types for truncated / garbage files; a bad config
        raise D2TurbError(f"{path}: corrupt weights file ({exc.__class__.__name__})") from exc
    return {"model": model, "params": int(params), "bytes": path.stat().st_size}
