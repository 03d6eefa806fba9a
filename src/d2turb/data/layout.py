"""On-disk layout of a generated pair dataset, shared by the generator, the checker and the loaders.

out/dataset.json                 config (version, pairs, patch, split, bins, seed, batch, depth, params)
out/meta.jsonl                   one JSON line per sample, sorted by index (written by the final merge)
out/.meta/rank-<r>.jsonl         per-rank append-only meta shards while generating (merged, then removed)
out/turb/<id>.png                8-bit RGB turbulent image (blur + tilt)
out/tilt/<id>.png                8-bit RGB tilt-only image (Eq. 8: blur module bypassed)
out/gt/<id>.png                  8-bit RGB clean crop
out/flow/<id>.npy                float16 (2, H, W) backward flow in px, x then y: warp(tilt, flow) ≈ gt
out/depth/<id>.png               16-bit grey relative depth, value = round(depth * 65535), far = 65535
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from d2turb.defaults import DEFAULT_PNG_LEVEL
from d2turb.errors import D2TurbError
from d2turb.io import float_array, write_image
from d2turb.sim import BINS

FORMAT_VERSION = 1
FILES = {"turb": ".png", "tilt": ".png", "gt": ".png", "flow": ".npy", "depth": ".png"}
META_NAME = "meta.jsonl"
CONFIG_NAME = "dataset.json"
SHARD_DIR = ".meta"
BIN_NAMES = tuple(BINS)  # D/r0 strength bins, defined once in d2turb.sim.params


def bin_index(name: str) -> int:
    """Index of a strength bin's name in ``BIN_NAMES`` (-1 for a name that is no bin)."""
    return BIN_NAMES.index(name) if name in BIN_NAMES else -1


def sample_id(index: int) -> str:
    return f"{index:07d}"


def file_path(root: Path, kind: str, sid: str) -> Path:
    return Path(root) / kind / f"{sid}{FILES[kind]}"


def write_depth_png(path: Path, depth: torch.Tensor, png_level: int = DEFAULT_PNG_LEVEL) -> None:
    """(1, H, W) or (H, W) depth in [0, 1] → 16-bit PNG, atomically."""
    arr = np.round(np.clip(float_array(depth), 0, 1).reshape(depth.shape[-2:]).astype(np.float64) * 65535.0)
    write_image(path, arr.astype(np.uint16), png_level)


def read_depth_png(path: Path) -> torch.Tensor:
    """16-bit depth PNG → float32 (1, H, W) in [0, 1]."""
    with Image.open(path) as img:
        img.load()
        arr = np.asarray(img)
    if arr.ndim != 2:
        raise D2TurbError(f"{path}: depth must be a single-channel image, got shape {arr.shape}")
    scale = 65535.0 if arr.dtype in (np.uint16, np.int32) or img.mode.startswith("I") else 255.0
    return torch.from_numpy(arr.astype(np.float32) / scale)[None]


def read_config(root: Path) -> dict:
    path = Path(root) / CONFIG_NAME
    if not path.is_file():
        raise D2TurbError(f"{root}: not a d2turb dataset (no {CONFIG_NAME})")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise D2TurbError(f"{path}: unreadable ({exc})") from exc


def parse_meta_lines(data: bytes) -> list[dict]:
    """Complete, valid JSON lines of a meta file; a trailing partial line (killed writer) is dropped."""
    records = []
    for line in data.split(b"\n")[:-1]:  # text after the last newline is a partial line
        try:
            rec = json.loads(line)
        except (json.JSONDecodeError, UnicodeDecodeError):
            continue
        if isinstance(rec, dict) and "id" in rec:
            records.append(rec)
    return records


def read_meta(root: Path) -> list[dict]:
    path = Path(root) / META_NAME
    if not path.is_file():
        raise D2TurbError(f"{root}: no {META_NAME} (generation unfinished? rerun make-dataset)")
    return parse_meta_lines(path.read_bytes())


def append_line(path: Path, record: dict) -> None:
    """Append one JSON line durably (flush + fsync), so a kill leaves at most one partial last line."""
    with open(path, "ab") as f:
        f.write((json.dumps(record, sort_keys=True) + "\n").encode())
        f.flush()
        os.fsync(f.fileno())


def truncate_partial_line(path: Path) -> None:
    """Cut a trailing partial line left by a killed writer."""
    if not path.is_file():
        return
    data = path.read_bytes()
    end = data.rfind(b"\n") + 1
    if end != len(data):
        with open(path, "r+b") as f:
            f.truncate(end)
