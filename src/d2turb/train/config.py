"""Training configuration: YAML file → defaults deep-merged → ``--set key=value`` overrides → validated dict.

Every section except ``model`` (free keyword arguments of the model) has a fixed set of keys; an unknown key is a
one-line :class:`D2TurbError`, so a typo never silently trains with a default.
"""

from __future__ import annotations

import copy
import os
from pathlib import Path

from d2turb.errors import D2TurbError

DEFAULTS: dict = {
    "model": {"name": "d2turb"},  # + create_model keyword arguments
    "data": {
        "pairs": None,  # PairDataset folder (random `patch` crop + flips)
        "clean": None,  # list of clean image folders/files for on-the-fly synthesis
        "on_the_fly": {
            "bins": ["weak", "medium", "strong"],
            "depth": "prior",
            "length": None,
            "params": {},
            "geometry": "fixed",  # d2turb.sim.geometry.GEOMETRIES name; one geometry drawn per batch
        },
        "patch": 256,
        "hflip": True,
        "vflip": False,
        "num_workers": 2,
    },
    "train": {
        "epochs": None,  # exactly one of epochs / iterations
        "iterations": None,
        "batch": 8,  # total over all processes; per-process batch = batch / world size
        "lr": 1.0e-4,  # Adam, cosine annealing lr → lr_min over the whole run
        "lr_min": 1.0e-6,
        "betas": [0.9, 0.999],
        "weight_decay": 0.0,
        "grad_clip": None,  # max global gradient norm, or null
        "amp": None,  # "bf16" (autocast of the forward pass; meant for CUDA, works on CPU) or null
        "seed": 0,
        "device": "auto",  # auto | cpu | cuda
    },
    "loss": {
        "deblur": 1.0,  # weight of L_deblur (0 = the paper's "w/o L_deblur" ablation)
        "native": None,  # the backbone's native loss (l1 | psnr); null = the backbone's registry entry
        "flow": 5.0,  # λ_flow (Eq. 14)
        "photo": 1.0,  # λ_photo (Eq. 13)
        "vgg": 0.02,  # λ_vgg (Eq. 13)
        "vgg_weights": None,  # local torchvision vgg16 weights; null → perceptual term disabled (one warning)
    },
    "val": {"pairs": None, "every": 1000, "max_images": None, "crop": None, "batch": 1},
    "log": {"every": 10, "progress": True},
    "checkpoint": {"every": 1000},
}


def _merge(base: dict, update: dict, where: str, free: bool = False) -> dict:
    out = copy.deepcopy(base)
    for key, value in update.items():
        name = f"{where}.{key}" if where else str(key)
        if key not in base and not free:
            raise D2TurbError(f"unknown config key {name!r}; allowed in {where or 'top level'}: {', '.join(base)}")
        if isinstance(base.get(key), dict) and key != "params":
            if not isinstance(value, dict):
                raise D2TurbError(f"config key {name!r} must be a mapping, got {value!r}")
            out[key] = _merge(base[key], value, name, free=(name == "model"))
        else:
            out[key] = copy.deepcopy(value)
    return out


def parse_override(item: str) -> tuple[list[str], object]:
    """``a.b.c=value`` → (["a", "b", "c"], value parsed as YAML)."""
    import yaml

    if "=" not in item:
        raise D2TurbError(f"--set {item!r}: expected key=value (e.g. train.iterations=100)")
    key, text = item.split("=", 1)
    if not key or any(not part for part in key.split(".")):
        raise D2TurbError(f"--set {item!r}: empty key")
    try:
        value = yaml.safe_load(text) if text else None
    except yaml.YAMLError:
        value = text
    return key.split("."), _number(value)


def _number(value):
    """YAML 1.1 reads ``1e-4`` (no dot) as a string; turn such strings into floats."""
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value
    return value


def _nest(path: list[str], value) -> dict:
    out: dict = {path[-1]: value}
    for part in reversed(path[:-1]):
        out = {part: out}
    return out


def load_config(
    path: str | os.PathLike | None = None, overrides: list[str] | tuple = (), base: dict | None = None
) -> dict:
    """Read a YAML config (or start from ``base``), merge it onto :data:`DEFAULTS`, apply ``key=value`` overrides,
    validate. Relative data paths are kept as written (resolved against the working directory)."""
    import yaml

    user: dict = copy.deepcopy(base) if base is not None else {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise D2TurbError(f"config file not found: {path}")
        try:
            user = yaml.safe_load(path.read_text()) or {}
        except (yaml.YAMLError, UnicodeDecodeError) as exc:
            raise D2TurbError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
        if not isinstance(user, dict):
            raise D2TurbError(f"{path}: the config must be a YAML mapping")
    cfg = _merge(DEFAULTS, user, "")
    for item in overrides:
        keys, value = parse_override(item)
        cfg = _merge(cfg, _nest(keys, value), "")
    validate(cfg)
    return cfg


def validate(cfg: dict) -> None:
    model, data, train, loss = cfg["model"], cfg["data"], cfg["train"], cfg["loss"]
    if not isinstance(model.get("name"), str):
        raise D2TurbError("config: model.name must be a model name (see `d2turb models`)")
    if (data["pairs"] is None) == (data["clean"] is None):
        raise D2TurbError("config: give exactly one of data.pairs (dataset folder) or data.clean (clean image folders)")
    if data["clean"] is not None and isinstance(data["clean"], str):
        data["clean"] = [data["clean"]]
    if (train["epochs"] is None) == (train["iterations"] is None):
        raise D2TurbError("config: give exactly one of train.epochs or train.iterations")
    for key in ("epochs", "iterations", "batch"):
        value = train[key]
        if value is not None and (not isinstance(value, int) or isinstance(value, bool) or value < 1):
            raise D2TurbError(f"config: train.{key} must be a positive integer, got {value!r}")
    for key in ("lr", "lr_min", "grad_clip"):
        train[key] = _number(train[key])
    for key in ("deblur", "flow", "photo", "vgg"):
        loss[key] = _number(loss[key])
    for key in ("lr", "lr_min"):
        if not isinstance(train[key], (int, float)) or train[key] < 0:
            raise D2TurbError(f"config: train.{key} must be a non-negative number, got {train[key]!r}")
    if train["amp"] not in (None, "bf16"):
        raise D2TurbError(f"config: train.amp must be bf16 or null, got {train['amp']!r}")
    for key in ("deblur", "flow", "photo", "vgg"):
        if not isinstance(loss[key], (int, float)) or loss[key] < 0:
            raise D2TurbError(f"config: loss.{key} must be a non-negative number, got {loss[key]!r}")
    for section, key in (("val", "every"), ("log", "every"), ("checkpoint", "every"), ("val", "batch")):
        value = cfg[section][key]
        if not isinstance(value, int) or value < 1:
            raise D2TurbError(f"config: {section}.{key} must be a positive integer, got {value!r}")
    if not isinstance(data["patch"], int) or data["patch"] < 16:
        raise D2TurbError(f"config: data.patch must be an integer >= 16, got {data['patch']!r}")


def model_kwargs(cfg: dict) -> tuple[str, dict]:
    kwargs = dict(cfg["model"])
    return kwargs.pop("name"), kwargs
