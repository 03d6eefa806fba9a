"""make-dataset's settings (:class:`DatasetConfig`), their checks, and the record of them that dataset.json keeps (a
rerun into the same folder must match it to resume)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from d2turb.data.field import FIELD_RANGES
from d2turb.data.layout import FILES, FORMAT_VERSION
from d2turb.data.sequence import sequence_settings
from d2turb.defaults import DEFAULT_DEPTH, DEFAULT_DEVICE
from d2turb.errors import D2TurbError
from d2turb.io import DEFAULT_PNG_LEVEL
from d2turb.sim.geometry import footprint_px
from d2turb.sim.params import BINS, bin_spans

SPLITS = ("train", "test")


@dataclass
class DatasetConfig:
    clean: list[str]
    out: str
    pairs: int
    patch: int = 256
    split: str = "train"
    bins: tuple[str, ...] = tuple(BINS)
    depth: str = DEFAULT_DEPTH
    depth_is_disparity: bool = False
    seed: int = 0
    batch: int = 8
    device: str = DEFAULT_DEVICE
    params: dict = field(default_factory=dict)  # TurbulenceParams overrides
    geometry: str = "fixed"  # a d2turb.sim.geometry.GEOMETRIES name; one geometry per chunk of `batch` samples
    png_level: int = DEFAULT_PNG_LEVEL  # zlib level of the PNG files (not part of the dataset's identity)
    frames: int = 1  # > 1: sequence samples (d2turb.data.sequence)
    sequence: dict = field(default_factory=dict)  # fps, wind, wind_dir, boil
    # camera degradation of the turbulent frames, drawn per sample: {"noise": [lo, hi] grey levels (σ of Gaussian
    # noise on the 0–255 scale), "jpeg": [lo, hi] JPEG quality}; empty: none (issue 35's blind test set)
    camera: dict = field(default_factory=dict)
    # "field": field-realistic clips (camera shake, moving objects, a camera in linear light; d2turb.data.field)
    profile: str = "standard"


PROFILES = ("standard", "field")


PATCH_MAX = 4096  # as train's data.patch: one 4096² sample already holds ~0.5 GB of float32 intermediates


def validate(cfg: DatasetConfig) -> None:
    if cfg.pairs < 1:
        raise D2TurbError(f"pairs must be at least 1, got {cfg.pairs}", param="pairs")
    if not 16 <= cfg.patch <= PATCH_MAX:
        raise D2TurbError(f"patch must be from 16 to {PATCH_MAX} px, got {cfg.patch}", param="patch")
    if cfg.split not in SPLITS:
        raise D2TurbError(f"split must be one of {', '.join(SPLITS)}, got {cfg.split!r}", param="split")
    bin_spans(cfg.bins)
    if cfg.batch < 1:
        raise D2TurbError(f"batch must be at least 1, got {cfg.batch}", param="batch")
    if not 0 <= cfg.seed < 2**63:
        raise D2TurbError(f"seed must be between 0 and 2**63 - 1, got {cfg.seed}", param="seed")
    if cfg.frames != 1 or cfg.sequence:
        cfg.sequence = sequence_settings(cfg.frames, cfg.sequence)
    for key, (lo_ok, hi_ok) in {"noise": (0.0, 50.0), "jpeg": (1, 100)}.items():
        span = cfg.camera.get(key)
        if span is not None and not (len(span) == 2 and lo_ok <= span[0] <= span[1] <= hi_ok):
            raise D2TurbError(f"camera {key} must be a range lo,hi within [{lo_ok:g}, {hi_ok:g}], got {span!r}")
    if set(cfg.camera) - {"noise", "jpeg"}:
        raise D2TurbError(f"unknown camera settings {sorted(set(cfg.camera) - {'noise', 'jpeg'})}")
    if cfg.profile not in PROFILES:
        raise D2TurbError(f"profile must be one of {', '.join(PROFILES)}, got {cfg.profile!r}", param="profile")
    if cfg.profile == "field":
        if cfg.frames < 2:
            raise D2TurbError("the field profile makes clips: give --frames N (N >= 2)", param="frames")
        if cfg.camera:
            raise D2TurbError("the field profile draws its own camera: leave out --camera-noise and --jpeg")


PER_SAMPLE_KEYS = ("dr0", "r0_m")  # drawn per sample (its bin): the record's "dr0", not the simulator's default


def params_record(params) -> dict:
    """TurbulenceParams as a JSON-ready dict (with the tilt footprint) for the metadata, without D/r0 and r0: each
    sample draws its own D/r0 from its bin (the sample's ``dr0`` field), so the simulator's default would only
    stand beside the true value as a second, wrong one."""
    full = {**params.to_dict(), "footprint_px": footprint_px(params)}
    full = {k: v for k, v in full.items() if k not in PER_SAMPLE_KEYS}
    return json.loads(json.dumps(full, default=str))


def dataset_config_record(cfg: DatasetConfig, sources: list[Path], params_full: dict) -> dict:
    sequence = {"frames": cfg.frames, "sequence": cfg.sequence} if cfg.frames > 1 else {}
    camera = {"camera": cfg.camera} if cfg.camera else {}
    if cfg.profile == "field":
        camera["profile"] = "field"
        camera["field"] = FIELD_RANGES
    return {
        **sequence,
        **camera,
        "version": FORMAT_VERSION,
        "pairs": cfg.pairs,
        "patch": cfg.patch,
        "split": cfg.split,
        "bins": list(cfg.bins),
        "bin_ranges": {b: list(BINS[b]) for b in cfg.bins},
        "seed": cfg.seed,
        "batch": cfg.batch,
        "depth": cfg.depth,
        "depth_is_disparity": cfg.depth_is_disparity,
        "params": params_full,
        "geometry": cfg.geometry,
        "clean": [str(c) for c in cfg.clean],
        "sources": len(sources),
        "files": {k: f"{k}/<id>{s}" for k, s in FILES.items()},
        "bwd_flow_px": "float16 (2,H,W) backward flow in px, x then y: warp(tilt, bwd_flow_px) ~ gt",
        "depth_encoding": "16-bit PNG, depth = value / 65535, far = 1",
    }
