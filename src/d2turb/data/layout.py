"""On-disk layout of a generated pair dataset, shared by the generator, the checker and the loaders.

out/dataset.json                 config (version, pairs, patch, split, bins, seed, batch, depth, params)
out/meta.jsonl                   one JSON line per sample, sorted by index (written by the final merge)
out/.meta/rank-<r>.jsonl         per-rank append-only meta shards while generating (merged, then removed)
out/turb/<id>.png                8-bit RGB turbulent image (blur + tilt)
out/tilt/<id>.png                8-bit RGB tilt-only image (Eq. 8: blur module bypassed)
out/gt/<id>.png                  8-bit RGB clean crop
out/bwd_flow_px/<id>.npy         float16 (2, H, W) backward flow in px, x then y: warp(tilt, bwd_flow_px) ≈ gt
out/depth/<id>.png               16-bit grey relative depth, value = round(depth * 65535), far = 65535

Datasets written before the flows were named by direction hold the same backward flows in ``out/flow/<id>.npy``;
:func:`file_path` still finds them there (a ``DeprecationWarning`` once per process).
"""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from d2turb.defaults import DEFAULT_PNG_LEVEL
from d2turb.deprecation import AliasDict, warn_once
from d2turb.errors import D2TurbError
from d2turb.io import float_array, write_image
from d2turb.sim import BINS

FORMAT_VERSION = 1
PATCH_MAX = 16384  # a dataset.json patch beyond this is damaged (make-dataset crops are far smaller)
FILES = {"turb": ".png", "tilt": ".png", "gt": ".png", "bwd_flow_px": ".npy", "depth": ".png"}
LEGACY_FOLDERS = {"bwd_flow_px": "flow"}  # a kind's folder in datasets written by earlier versions
META_NAME = "meta.jsonl"
CONFIG_NAME = "dataset.json"
SHARD_DIR = ".meta"
BIN_NAMES = tuple(BINS)  # D/r0 strength bins, defined once in d2turb.sim.params


class Sample(AliasDict):
    """A dataset sample (dict): one key per tensor; ``flow``, the deprecated name of ``bwd_flow_px``, still reads it
    with a ``DeprecationWarning`` (once)."""

    aliases = {"flow": "bwd_flow_px"}
    what = "dataset sample"


def bin_index(name: str) -> int:
    """Index of a strength bin's name in ``BIN_NAMES`` (-1 for a name that is no bin)."""
    return BIN_NAMES.index(name) if name in BIN_NAMES else -1


def sample_id(index: int) -> str:
    return f"{index:07d}"


_NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")


def check_sample_id(sid) -> str:
    """A sample id as a file name: one plain path component (letters, digits, ``_ . -``, not starting with a dot),
    so that every path made from it stays inside the dataset folder. Raises ``ValueError`` otherwise."""
    if not isinstance(sid, str) or not _NAME_RE.fullmatch(sid) or len(sid) > 200:
        raise ValueError(f"id {json.dumps(sid)} is not a plain file name (letters, digits, _ . -)")
    return sid


def inside(root: str | os.PathLike, relative, what: str) -> Path:
    """``root / relative`` for a relative path read from a dataset or pack file, refused (``D2TurbError`` naming
    ``what``) unless it stays inside ``root``: a string of ``/``-separated names, none empty, ``.`` or ``..``, no
    backslash or NUL, not absolute. The one check of every path that a dataset's own files name."""
    parts = relative.split("/") if isinstance(relative, str) else None
    if not parts or any(part in ("", ".", "..") or "\\" in part or "\0" in part for part in parts):
        raise D2TurbError(f"{what}: path {json.dumps(relative)} is not a plain relative path inside {root}")
    return Path(root).joinpath(*parts)


def file_path(root: Path, kind: str, sid: str) -> Path:
    """``root/kind/<sid><ext>``; for a dataset of the earlier layout (``flow/<sid>.npy`` there, no
    ``bwd_flow_px/<sid>.npy``) the earlier file, with a ``DeprecationWarning`` once. The kind ``flow`` is the
    deprecated name of ``bwd_flow_px``."""
    try:
        check_sample_id(sid)
    except ValueError as exc:
        raise D2TurbError(f"{root}: {exc}") from exc
    if kind == "flow":
        warn_once("file_path(flow)", "the dataset file kind 'flow' is deprecated; use 'bwd_flow_px'")
        kind = "bwd_flow_px"
    path = Path(root) / kind / f"{sid}{FILES[kind]}"
    legacy = LEGACY_FOLDERS.get(kind)
    if legacy is not None and not path.exists():
        old = Path(root) / legacy / path.name
        if old.exists():
            warn_once(
                "dataset flow/",
                f"{root}: a dataset of the earlier layout; its flow/<id>.npy (backward flows) is read as "
                "bwd_flow_px/<id>.npy, the name make-dataset now writes (rename the folder to silence this)",
            )
            return old
    return path


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


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as exc:
        raise D2TurbError(f"{path}: cannot read ({exc.strerror or exc.__class__.__name__})") from exc


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def check_config(cfg) -> dict:
    """The fields of ``dataset.json`` that readers use, checked: a mapping with ``patch`` an integer from 1 to
    PATCH_MAX, ``pairs`` (when present) a non-negative integer, ``frames`` (when present) a positive integer,
    ``split`` (when present) a string. Raises ``ValueError`` naming the field."""
    if not isinstance(cfg, dict):
        raise ValueError(f"must be a JSON object, not {type(cfg).__name__}")
    if "patch" not in cfg:
        raise ValueError("no patch size ('patch')")
    if not _is_int(cfg["patch"]) or not 1 <= cfg["patch"] <= PATCH_MAX:
        raise ValueError(f"patch must be an integer from 1 to {PATCH_MAX}, got {json.dumps(cfg['patch'])}")
    if "pairs" in cfg and (not _is_int(cfg["pairs"]) or cfg["pairs"] < 0):
        raise ValueError(f"pairs must be a non-negative integer, got {json.dumps(cfg['pairs'])}")
    if "frames" in cfg and (not _is_int(cfg["frames"]) or not 1 <= cfg["frames"] <= 10_000):
        raise ValueError(f"frames must be an integer from 1 to 10000, got {json.dumps(cfg['frames'])}")
    if "split" in cfg and not isinstance(cfg["split"], str):
        raise ValueError(f"split must be a string, got {json.dumps(cfg['split'])}")
    return cfg


def check_record(rec) -> dict:
    """One sample record of ``meta.jsonl``, checked: a mapping with ``id`` a plain file name
    (:func:`check_sample_id`), ``index`` a non-negative integer, ``dr0`` a finite number, ``bin`` a string.
    Raises ``ValueError`` naming the field."""
    if not isinstance(rec, dict):
        raise ValueError(f"not a JSON object: {json.dumps(rec)[:80]}")
    for key in ("id", "index", "dr0", "bin"):
        if key not in rec:
            raise ValueError(f"no {key!r}")
    check_sample_id(rec["id"])
    if not _is_int(rec["index"]) or rec["index"] < 0:
        raise ValueError(f"index must be a non-negative integer, got {json.dumps(rec['index'])}")
    dr0 = rec["dr0"]
    if not isinstance(dr0, (int, float)) or isinstance(dr0, bool) or not math.isfinite(dr0):
        raise ValueError(f"dr0 must be a finite number, got {json.dumps(dr0)}")
    if not isinstance(rec["bin"], str):
        raise ValueError(f"bin must be a string, got {json.dumps(rec['bin'])}")
    return rec


def load_flow(path: Path) -> np.ndarray:
    """A dataset's backward flow ``.npy`` (``bwd_flow_px/<id>.npy``) as float32 (no pickles); a file that does not
    load, or holds no finite float array, is a ``D2TurbError`` naming it."""
    try:
        bwd_flow_px = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise D2TurbError(f"{path}: cannot read flow ({exc.__class__.__name__}: {exc})") from exc
    if not isinstance(bwd_flow_px, np.ndarray) or bwd_flow_px.dtype.kind != "f":
        got = getattr(bwd_flow_px, "dtype", type(bwd_flow_px).__name__)
        raise D2TurbError(f"{path}: flow must be a float array, got {got}")
    bwd_flow_px = bwd_flow_px.astype(np.float32)
    if not np.isfinite(bwd_flow_px).all():
        raise D2TurbError(f"{path}: flow contains NaN or infinite values")
    return bwd_flow_px


def read_config(root: Path) -> dict:
    """``dataset.json`` of ``root``, checked by :func:`check_config`; ``D2TurbError`` in one line otherwise."""
    path = Path(root) / CONFIG_NAME
    if not path.is_file():
        raise D2TurbError(f"{root}: not a d2turb dataset (no {CONFIG_NAME})")
    try:
        return check_config(json.loads(_read_bytes(path)))
    except D2TurbError:
        raise
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise D2TurbError(f"{path}: unreadable ({exc})") from exc
    except ValueError as exc:
        raise D2TurbError(f"{path}: not a valid dataset config: {exc}") from exc


def open_split(root, split: str | None) -> tuple[Path, dict]:
    """The dataset folder (``root``, or ``root/<split>`` when that holds a dataset) and its checked ``dataset.json``;
    a ``split`` the data was not made as is a ``D2TurbError``."""
    root = Path(root)
    if split is not None and (root / split / CONFIG_NAME).is_file():
        root = root / split  # a parent folder holding train/ and test/
    config = read_config(root)
    if split is not None and config.get("split") != split:
        raise D2TurbError(f"{root}: dataset split is {config.get('split')!r}, not {split!r}")
    return root, config


def record_entries(root: Path, rec: dict) -> dict:
    """The entries of a sample besides its images and flow, as the datasets give them: depth (1, H, W) in [0, 1],
    dr0 float32 scalar, bin int64 scalar (index into the bin names), id str."""
    sid = rec["id"]
    return {
        "depth": read_depth_png(file_path(root, "depth", sid)),
        "dr0": torch.tensor(float(rec["dr0"]), dtype=torch.float32),
        "bin": torch.tensor(bin_index(rec["bin"]), dtype=torch.int64),
        "id": sid,
    }


def parse_meta_lines(data: bytes) -> list[dict]:
    """Complete, valid records of a meta file (:func:`check_record`); a trailing partial line (killed writer)
    and invalid lines are dropped (the generator's resume state: a dropped sample is made again)."""
    records = []
    for line in data.split(b"\n")[:-1]:  # text after the last newline is a partial line
        try:
            records.append(check_record(json.loads(line)))
        except (json.JSONDecodeError, UnicodeDecodeError, ValueError):
            continue
    return records


def iter_meta(path: Path):
    """(line number, record or None, problem or None) for each non-blank line of a meta file, each record
    checked by :func:`check_record`: the one reading of ``meta.jsonl`` that loaders and the checker share."""
    for n, line in enumerate(_read_bytes(path).split(b"\n"), 1):
        if not line.strip():
            continue
        try:
            yield n, check_record(json.loads(line)), None
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            yield n, None, f"not valid JSON ({exc.__class__.__name__})"
        except ValueError as exc:
            yield n, None, f"not a valid sample record: {exc}"


def read_meta(root: Path, invalid: list | None = None) -> list[dict]:
    """The records of ``meta.jsonl``; the first invalid line (a damaged file, an id that would name a path outside
    the folder) is a one-line ``D2TurbError`` naming the file and line. With a list ``invalid``, invalid lines are
    skipped instead and their messages appended to it (evaluate reports them and goes on)."""
    path = Path(root) / META_NAME
    if not path.is_file():
        raise D2TurbError(f"{root}: no {META_NAME} (generation unfinished? rerun make-dataset)")
    records = []
    for n, rec, problem in iter_meta(path):
        if problem is not None:
            message = f"{path} line {n}: {problem}; check it with `d2turb check-dataset {root}`"
            if invalid is None:
                raise D2TurbError(message)
            invalid.append(message)
            continue
        records.append(rec)
    return records


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
