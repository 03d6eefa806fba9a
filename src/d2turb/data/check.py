"""Verification of a generated pair dataset (``d2turb check-dataset``)."""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

from d2turb.data.layout import (
    CONFIG_NAME,
    FILES,
    LEGACY_FOLDERS,
    META_NAME,
    SHARD_DIR,
    file_path,
    iter_meta,
    read_config,
    read_depth_png,
)
from d2turb.errors import D2TurbError


@dataclass
class CheckReport:
    samples: int = 0
    counts: dict[str, int] = field(default_factory=dict)  # samples per bin
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


def _check_sample(
    root: Path, rec: dict, patch: int, decode: bool, frames: int = 1, gt_per_frame: bool = False
) -> list[str]:
    """``frames`` > 1: turb/tilt are filmstrips (frames·patch tall), flow is (frames, 2, patch, patch);
    ``gt_per_frame`` (the field profile): gt is a filmstrip too."""
    sid, problems = rec["id"], []
    for kind in FILES:
        if not file_path(root, kind, sid).is_file():
            problems.append(f"{sid}: missing {kind}/{sid}{FILES[kind]}")
    if problems or not decode:
        return problems
    for kind in ("turb", "tilt", "gt"):
        tall = patch * (frames if kind != "gt" or gt_per_frame else 1)
        try:
            with Image.open(file_path(root, kind, sid)) as img:
                img.load()
                if img.mode != "RGB" or img.size != (patch, tall):
                    problems.append(
                        f"{sid}: {kind} is {img.mode} {img.size[0]}x{img.size[1]}, expected RGB {patch}x{tall}"
                    )
        except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as exc:
            problems.append(f"{sid}: {kind} does not decode ({exc.__class__.__name__})")
    try:
        bwd_flow_px = np.load(file_path(root, "bwd_flow_px", sid), allow_pickle=False)
        shape = (2, patch, patch) if frames == 1 else (frames, 2, patch, patch)
        if bwd_flow_px.shape != shape or bwd_flow_px.dtype != np.float16:
            problems.append(f"{sid}: bwd_flow_px is {bwd_flow_px.dtype} {bwd_flow_px.shape}, expected float16 {shape}")
        elif not np.isfinite(bwd_flow_px).all():
            problems.append(f"{sid}: bwd_flow_px contains NaN or infinite values")
    except (OSError, ValueError, EOFError) as exc:
        problems.append(f"{sid}: bwd_flow_px does not load ({exc.__class__.__name__})")
    try:
        depth = read_depth_png(file_path(root, "depth", sid))
        if tuple(depth.shape) != (1, patch, patch):
            problems.append(f"{sid}: depth is {tuple(depth.shape[-2:])}, expected ({patch}, {patch})")
    except (OSError, SyntaxError, ValueError, D2TurbError, Image.DecompressionBombError) as exc:
        problems.append(f"{sid}: depth does not decode ({exc.__class__.__name__})")
    return problems


def _bin_ranges(value) -> dict[str, tuple[float, float]]:
    """``bin_ranges`` of dataset.json: {name: [low, high]} with finite low <= high."""
    if not isinstance(value, dict) or not value:
        raise TypeError(f"bin_ranges must be an object of [low, high] pairs, got {json.dumps(value)}")
    ranges = {}
    for name, pair in value.items():
        if not isinstance(pair, list) or len(pair) != 2 or not all(isinstance(v, (int, float)) for v in pair):
            raise TypeError(f"bin_ranges[{name!r}] must be [low, high], got {json.dumps(pair)}")
        lo, hi = float(pair[0]), float(pair[1])
        if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi):
            raise ValueError(f"bin_ranges[{name!r}] = {pair} is not a finite range")
        ranges[str(name)] = (lo, hi)
    return ranges


def check_dataset(root: str | Path, decode: bool = True) -> CheckReport:
    """Every meta id has all its files and they decode with the right shapes, no NaN in flow,
    no orphan files, no duplicate ids, D/r0 inside the stated bin, as many samples as configured."""
    root = Path(root)
    if not root.is_dir():
        raise D2TurbError(f"{root}: not a directory")
    if not (root / CONFIG_NAME).is_file():
        raise D2TurbError(f"{root}: not a d2turb dataset (no {CONFIG_NAME})")
    cfg = read_config(root)  # the checks every reader of a dataset applies
    try:
        patch, pairs, ranges = cfg["patch"], cfg["pairs"], _bin_ranges(cfg["bin_ranges"])
        frames = cfg.get("frames", 1)
    except (KeyError, TypeError, ValueError) as exc:
        raise D2TurbError(f"{root / CONFIG_NAME}: unreadable dataset config ({exc.__class__.__name__}: {exc})") from exc
    report = CheckReport(counts={b: 0 for b in sorted(ranges, key=lambda b: ranges[b][0])})
    problems = report.problems
    meta_path = root / META_NAME
    if not meta_path.is_file():
        problems.append(f"no {META_NAME}: generation unfinished (rerun make-dataset with the same arguments)")
        return report
    if (root / SHARD_DIR).is_dir() and any((root / SHARD_DIR).iterdir()):
        problems.append(f"unmerged meta shards in {SHARD_DIR}/: generation unfinished (rerun make-dataset)")

    ids: Counter[str] = Counter()
    records = []
    for n, rec, problem in iter_meta(meta_path):  # the checks every reader of a dataset applies
        if problem is not None:
            problems.append(f"{META_NAME} line {n}: {problem}")
            continue
        sid, dr0, name = rec["id"], float(rec["dr0"]), rec["bin"]
        ids[sid] += 1
        if ids[sid] > 1:
            problems.append(f"{sid}: duplicate id in {META_NAME} (line {n})")
            continue
        records.append(rec)
        if name not in ranges:
            problems.append(f"{sid}: bin {name!r} is not one of the dataset's bins ({', '.join(ranges)})")
        elif not ranges[name][0] <= dr0 <= ranges[name][1] or not np.isfinite(dr0):
            problems.append(f"{sid}: D/r0 = {dr0:.4f} lies outside its bin {name} {list(ranges[name])}")
        else:
            report.counts[name] += 1
    for rec in records:
        problems.extend(_check_sample(root, rec, patch, decode, frames, cfg.get("profile") == "field"))
    report.samples = len(records)
    if report.samples != pairs:
        problems.append(f"{report.samples} samples in {META_NAME}, expected {pairs}")
    folders = [(kind, suffix) for kind, suffix in FILES.items()]
    folders += [(LEGACY_FOLDERS[kind], FILES[kind]) for kind in LEGACY_FOLDERS]  # an earlier layout's
    for kind, suffix in folders:
        folder = root / kind
        if not folder.is_dir():
            continue
        for p in sorted(folder.iterdir()):
            if p.name.startswith(".") or p.suffix != suffix or p.stem not in ids:
                problems.append(f"orphan file {kind}/{p.name} (no meta record)")
    return report
