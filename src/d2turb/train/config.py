"""Training configuration, typed: YAML file → defaults deep-merged → ``--set key=value`` overrides → :class:`Config`.

Every section except ``model`` (free keyword arguments of the model) and ``data.on_the_fly.params`` (simulator
overrides) has a fixed set of keys, the fields of its dataclass; an unknown key is a one-line
:class:`D2TurbError`, so a typo never silently trains with a default. :meth:`Config.from_dict` builds a new,
validated object and never modifies the mapping it is given.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from d2turb.errors import D2TurbError
from d2turb.sim.geometry import GEOMETRIES
from d2turb.sim.params import BINS

PATCH_MAX = 4096  # training crops: a 4096² batch of 8 already needs gigabytes per activation
SEED_MAX = 2**63 - 1  # torch generators take [0, 2**63 - 1] (as d2turb.commands.common.SEED_MAX)


@dataclass
class OnTheFlyConfig:
    """Synthesis of training pairs on the training device (``data.clean`` or ``data.pack``)."""

    bins: list[str] = field(default_factory=lambda: list(BINS))
    depth: str = "prior"  # none | prior | DIR | anything:PATH
    length: int | None = None  # crops per epoch (default: one per image)
    params: dict = field(default_factory=dict)  # TurbulenceParams overrides
    geometry: str = "fixed"  # d2turb.sim.geometry.GEOMETRIES name; one imaging geometry drawn per batch


@dataclass
class DataConfig:
    """Exactly one source: ``pairs`` (a make-dataset folder), ``clean`` (image folders) or ``pack`` (make-pack)."""

    pairs: str | None = None
    clean: list[str] | None = None
    pack: str | None = None
    on_the_fly: OnTheFlyConfig = field(default_factory=OnTheFlyConfig)
    patch: int = 256
    hflip: bool = True
    vflip: bool = False
    num_workers: int = 2  # pairs / clean only; a pack lives in memory on the training device

    @property
    def source(self) -> str:
        """``pairs`` | ``clean`` | ``pack``."""
        return next(k for k in ("pairs", "clean", "pack") if getattr(self, k) is not None)


@dataclass
class TrainConfig:
    epochs: int | None = None  # exactly one of epochs / iterations
    iterations: int | None = None
    batch: int = 8  # total over all processes; per-process batch = batch / world size
    lr: float = 1.0e-4  # Adam, cosine annealing lr → lr_min over the whole run
    lr_min: float = 1.0e-6
    betas: list[float] = field(default_factory=lambda: [0.9, 0.999])
    weight_decay: float = 0.0
    grad_clip: float | None = None  # max global gradient norm, or null
    amp: str | None = None  # "bf16": autocast of the forward pass (meant for CUDA, runs on CPU), or null
    channels_last: bool = False  # NHWC memory format for the model and its input
    compile: bool | str = False  # torch.compile the forward (true = inductor, or a backend name)
    ema: float | None = None  # EMA decay of the weights (e.g. 0.999); EMA weights validate and ship
    max_minutes: float | None = None  # time budget: checkpoint and exit cleanly after this many minutes
    init_from: str | None = None  # start from these weights (name or .safetensors), ignored when resuming
    seed: int = 0
    device: str = "auto"  # auto | cpu | cuda


@dataclass
class LossConfig:
    deblur: float = 1.0  # weight of L_deblur (0 = the paper's "w/o L_deblur" ablation)
    native: str | None = None  # the backbone's native loss (l1 | psnr); null = the backbone's registry entry
    flow: float = 5.0  # λ_flow (Eq. 14)
    photo: float = 1.0  # λ_photo (Eq. 13)
    vgg: float = 0.02  # λ_vgg (Eq. 13)
    vgg_weights: str | None = None  # local torchvision vgg16 weights; null → perceptual term disabled (one warning)
    spectral: float = 0.0  # λ_spec: L1 of the Fourier amplitudes against I_gt (beyond the paper; losses.py)


@dataclass
class ValConfig:
    """At most one source: ``pairs`` (make-dataset --split test folder) or ``pack`` (its val images, synthesised
    once per bin with ``seed``)."""

    pairs: str | None = None
    pack: str | None = None
    every: int = 1000
    max_images: int | None = None
    crop: int | None = None  # centre crop (pack: default data.patch)
    batch: int = 1
    seed: int = 0


@dataclass
class LogConfig:
    every: int = 10
    progress: bool = True


@dataclass
class CheckpointConfig:
    every: int = 1000


@dataclass
class Config:
    model: dict = field(default_factory=lambda: {"name": "d2turb"})  # name + create_model keyword arguments
    data: DataConfig = field(default_factory=DataConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    val: ValConfig = field(default_factory=ValConfig)
    log: LogConfig = field(default_factory=LogConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)

    def to_dict(self) -> dict:
        """A plain, JSON/YAML-serialisable deep copy."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, raw: dict) -> Config:
        """Defaults + ``raw`` (unknown keys refused) → a new validated :class:`Config`; ``raw`` is not modified."""
        merged = _merge(DEFAULTS, raw, "")
        cfg = cls(
            model=merged["model"],
            data=_data_config(merged["data"]),
            train=TrainConfig(**_numbers(merged["train"], ("lr", "lr_min", "grad_clip", "weight_decay"))),
            loss=LossConfig(**_numbers(merged["loss"], ("deblur", "flow", "photo", "vgg", "spectral"))),
            val=ValConfig(**merged["val"]),
            log=LogConfig(**merged["log"]),
            checkpoint=CheckpointConfig(**merged["checkpoint"]),
        )
        validate(cfg)
        return cfg


def _data_config(data: dict) -> DataConfig:
    clean = data["clean"]
    fields = {k: v for k, v in data.items() if k not in ("on_the_fly", "clean")}
    return DataConfig(
        **fields,
        clean=[clean] if isinstance(clean, str) else clean,
        on_the_fly=OnTheFlyConfig(**data["on_the_fly"]),
    )


DEFAULTS: dict = Config().to_dict()
_FREE = ("model", "data.on_the_fly.params")  # sections whose keys are not fixed


def _merge(base: dict, update: dict, where: str, free: bool = False) -> dict:
    if not isinstance(update, dict):
        raise D2TurbError(f"config {where or 'file'} must be a mapping, got {update!r}")
    out = copy.deepcopy(base)
    for key, value in update.items():
        name = f"{where}.{key}" if where else str(key)
        if key not in base and not free:
            raise D2TurbError(f"unknown config key {name!r}; allowed in {where or 'top level'}: {', '.join(base)}")
        if isinstance(base.get(key), dict) and name not in _FREE[1:] and (isinstance(value, dict) or not free):
            if not isinstance(value, dict):
                raise D2TurbError(f"config key {name!r} must be a mapping, got {value!r}")
            out[key] = _merge(base[key], value, name, free=free or name in _FREE)
        else:
            out[key] = copy.deepcopy(value)
    return out


def parse_override(item: str) -> tuple[list[str], object]:
    """``a.b.c=value`` → (["a", "b", "c"], value parsed as YAML)."""
    import yaml

    if "=" not in item:
        raise D2TurbError(f"overrides {item!r}: expected key=value (e.g. train.iterations=100)", param="overrides")
    key, text = item.split("=", 1)
    if not key or any(not part for part in key.split(".")):
        raise D2TurbError(f"overrides {item!r}: empty key", param="overrides")
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


def _numbers(section: dict, keys: tuple[str, ...]) -> dict:
    return {k: (_number(v) if k in keys else v) for k, v in section.items()}


def _nest(path: list[str], value) -> dict:
    out: dict = {path[-1]: value}
    for part in reversed(path[:-1]):
        out = {part: out}
    return out


def load_config(
    path: str | os.PathLike | None = None, overrides: list[str] | tuple = (), base: dict | None = None
) -> Config:
    """Read a YAML config (or start from ``base``), merge it onto :data:`DEFAULTS`, apply ``key=value`` overrides,
    validate. Relative data paths are kept as written (resolved against the working directory).

    Args:
        path: YAML file, or None to start from ``base`` alone.
        overrides: ``dotted.key=value`` strings (values parsed as YAML).
        base: a mapping used instead of a file (not modified).

    Returns:
        The validated :class:`Config`.
    """
    import yaml

    user: dict = copy.deepcopy(base) if base is not None else {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise D2TurbError(f"config file not found: {path}")
        try:
            user = yaml.safe_load(path.read_text()) or {}
        except OSError as exc:
            raise D2TurbError(f"{path}: cannot read config ({exc.strerror or exc.__class__.__name__})") from exc
        except (yaml.YAMLError, UnicodeDecodeError) as exc:
            raise D2TurbError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from exc
        if not isinstance(user, dict):
            raise D2TurbError(f"{path}: the config must be a YAML mapping")
    user = _merge(DEFAULTS, user, "")
    for item in overrides:
        keys, value = parse_override(item)
        user = _merge(user, _nest(keys, value), "")
    return Config.from_dict(user)


def _positive_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 1


def _number_at_least(value: Any, low: float = 0.0) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and value >= low


def validate(cfg: Config) -> None:
    """Raise a one-line :class:`D2TurbError` for the first inconsistent value of ``cfg`` (nothing is changed)."""
    data, train, loss, val = cfg.data, cfg.train, cfg.loss, cfg.val
    if not isinstance(cfg.model.get("name"), str):
        raise D2TurbError("config: model.name must be a model name (see `d2turb models`)")
    if sum(getattr(data, k) is not None for k in ("pairs", "clean", "pack")) != 1:
        raise D2TurbError(
            "config: give exactly one of data.pairs (dataset folder), data.clean (clean image folders) "
            "or data.pack (a make-pack folder)"
        )
    if data.clean is not None and not (isinstance(data.clean, list) and all(isinstance(c, str) for c in data.clean)):
        raise D2TurbError(f"config: data.clean must be a folder or a list of folders, got {data.clean!r}")
    if not isinstance(data.patch, int) or isinstance(data.patch, bool) or not 16 <= data.patch <= PATCH_MAX:
        raise D2TurbError(
            f"config: data.patch must be an integer from 16 to {PATCH_MAX} (the paper trains on 256), "
            f"got {data.patch!r}"
        )
    if not isinstance(data.num_workers, int) or data.num_workers < 0:
        raise D2TurbError(f"config: data.num_workers must be a non-negative integer, got {data.num_workers!r}")
    otf = data.on_the_fly
    if not isinstance(otf.bins, list) or not otf.bins or not all(isinstance(b, str) for b in otf.bins):
        raise D2TurbError(f"config: data.on_the_fly.bins must be a non-empty list of bin names, got {otf.bins!r}")
    if otf.length is not None and not _positive_int(otf.length):
        raise D2TurbError(f"config: data.on_the_fly.length must be a positive integer, got {otf.length!r}")

    if otf.geometry not in GEOMETRIES:
        raise D2TurbError(
            f"config: data.on_the_fly.geometry must be one of {', '.join(GEOMETRIES)}, got {otf.geometry!r}"
        )
    if (train.epochs is None) == (train.iterations is None):
        raise D2TurbError("config: give exactly one of train.epochs or train.iterations")
    for key in ("epochs", "iterations", "batch"):
        value = getattr(train, key)
        if value is not None and not _positive_int(value):
            raise D2TurbError(f"config: train.{key} must be a positive integer, got {value!r}")
    for key in ("lr", "lr_min", "weight_decay"):
        value = getattr(train, key)
        if not _number_at_least(value) or not math.isfinite(value):
            raise D2TurbError(f"config: train.{key} must be a finite non-negative number, got {value!r}")
    if train.lr <= 0:
        raise D2TurbError(f"config: train.lr must be positive, got {train.lr!r}")
    if train.lr_min > train.lr:
        raise D2TurbError(
            f"config: train.lr_min ({train.lr_min!r}) must not exceed train.lr ({train.lr!r}): the cosine schedule "
            "anneals from train.lr down to train.lr_min"
        )
    for section, value in (("train", train.seed), ("val", val.seed)):
        if not isinstance(value, int) or isinstance(value, bool):
            raise D2TurbError(f"config: {section}.seed must be an integer, got {value!r}")
        if not 0 <= value <= SEED_MAX:
            raise D2TurbError(f"config: {section}.seed must be between 0 and 2**63 - 1, got {value}")
    if train.grad_clip is not None and not (_number_at_least(train.grad_clip) and train.grad_clip > 0):
        raise D2TurbError(f"config: train.grad_clip must be a positive number or null, got {train.grad_clip!r}")
    if not (
        isinstance(train.betas, (list, tuple))
        and len(train.betas) == 2
        and all(_number_at_least(b) and b < 1 for b in train.betas)
    ):
        raise D2TurbError(f"config: train.betas must be two numbers in [0, 1), got {train.betas!r}")
    if train.amp not in (None, "bf16"):
        raise D2TurbError(f"config: train.amp must be bf16 or null, got {train.amp!r}")
    if not isinstance(train.channels_last, bool):
        raise D2TurbError(f"config: train.channels_last must be true or false, got {train.channels_last!r}")
    if not isinstance(train.compile, (bool, str)) or train.compile == "":
        raise D2TurbError(
            f"config: train.compile must be true, false or a torch.compile backend, got {train.compile!r}"
        )
    if train.ema is not None and not (_number_at_least(train.ema) and 0 < train.ema < 1):
        raise D2TurbError(f"config: train.ema must be a decay in (0, 1) (e.g. 0.999) or null, got {train.ema!r}")
    if train.max_minutes is not None and not (_number_at_least(train.max_minutes) and train.max_minutes > 0):
        raise D2TurbError(f"config: train.max_minutes must be a positive number or null, got {train.max_minutes!r}")
    if train.init_from is not None and not isinstance(train.init_from, str):
        raise D2TurbError(f"config: train.init_from must be a weights name or file, got {train.init_from!r}")
    for key in ("deblur", "flow", "photo", "vgg", "spectral"):
        if not _number_at_least(getattr(loss, key)):
            raise D2TurbError(f"config: loss.{key} must be a non-negative number, got {getattr(loss, key)!r}")
    if val.pairs is not None and val.pack is not None:
        raise D2TurbError("config: give at most one of val.pairs or val.pack")
    for section, key in (("val", "every"), ("log", "every"), ("checkpoint", "every"), ("val", "batch")):
        value = getattr(getattr(cfg, section), key)
        if not _positive_int(value):
            raise D2TurbError(f"config: {section}.{key} must be a positive integer, got {value!r}")
    for key in ("max_images", "crop"):
        value = getattr(val, key)
        if value is not None and not _positive_int(value):
            raise D2TurbError(f"config: val.{key} must be a positive integer or null, got {value!r}")


def model_kwargs(cfg: Config) -> tuple[str, dict]:
    """(model name, create_model keyword arguments) of ``cfg``."""
    kwargs = copy.deepcopy(cfg.model)
    return kwargs.pop("name"), kwargs
