"""Training packs: the train and validation images of the fixed split (:mod:`d2turb.data.split`) as one compact,
self-describing folder, small enough to travel with a repository checkout to a GPU host (≤ ~40 MiB).

Layout: ``PACK/pack.json`` (manifest) and ``PACK/<split>/<folder>/<stem>.jpg``. Every image is re-encoded as a
baseline JPEG (``quality``, 4:2:0) after an optional Lanczos downscale to a common long-side cap; the cap is the
largest rung of :data:`LADDER` (at most ``max_side``) for which the whole pack fits ``max_mib``. The short side is
never brought below ``patch`` by the downscale. The manifest records, per image, its source (path, SHA-256, size,
and the provenance row of a ``MANIFEST.csv`` beside the folders when there is one), its split and the SHA-256 of
the stored file; it has no time stamps, so the same sources and options give a byte-identical pack.

Making a pack is atomic (built in ``.<name>.partial`` beside the output, then renamed) and restartable (encoded
images are cached in the partial folder, so a rerun after an interruption reuses them). Test folders are refused.
Reading a pack is :mod:`~d2turb.data.pack_read`: :class:`~d2turb.data.pack_read.PackCrops` decodes it once into
memory (uint8, on the training device) and serves random crops.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from d2turb.data.pack_read import KIND, MANIFEST, PACK_FORMAT, read_pack, sha256_file
from d2turb.data.split import TEST_FOLDERS, VAL_FOLDERS, split_of
from d2turb.errors import D2TurbError
from d2turb.io import list_images, read_image, to_uint8, write_bytes, write_text

MAX_MIB = 1 << 20  # --max-mib at most 1 TiB
LADDER: tuple[int | None, ...] = (None, 1024, 896, 768, 704, 640, 576, 512, 480, 448, 416, 384, 352, 320, 288, 256)
_MIB = 1 << 20


@dataclass(frozen=True)
class PackSource:
    """One clean image going into a pack."""

    path: Path
    folder: str  # the folder's name: decides the split
    split: str


def collect_sources(dirs: Sequence[str | os.PathLike]) -> tuple[list[PackSource], list[str]]:
    """The images of ``dirs`` with their split, and the names of test folders left out.

    Each DIR is a folder of images (named in the split definition), or a parent folder such as
    ``../shared/data/clean`` whose sub-folders are taken one by one; there, test folders are left out and
    reported. A test folder given by name is an error.

    Returns:
        (sources sorted by folder then file name, names of excluded test folders).
    """
    folders: dict[str, Path] = {}
    excluded: list[str] = []
    for item in dirs:
        root = Path(item)
        if not root.is_dir():
            raise D2TurbError(f"{root}: not a directory (make-pack takes folders of clean images)")
        subdirs = sorted(p for p in root.iterdir() if p.is_dir() and list_images(p))
        if list_images(root) or not subdirs:
            candidates = [root]
            if split_of(root) == "test":
                raise D2TurbError(
                    f"{root}: {root.name!r} is a test folder ({', '.join(TEST_FOLDERS)}); "
                    "a training pack holds only train and validation images"
                )
        else:
            candidates = [p for p in subdirs if split_of(p) != "test"]
            excluded += [p.name for p in subdirs if split_of(p) == "test"]
        for folder in candidates:
            if folder.name in folders and folders[folder.name].resolve() != folder.resolve():
                raise D2TurbError(f"two folders named {folder.name!r}: {folders[folder.name]} and {folder}")
            folders[folder.name] = folder
    sources = [
        PackSource(path, name, split_of(name)) for name in sorted(folders) for path in list_images(folders[name])
    ]
    if not sources:
        raise D2TurbError("no images found in " + ", ".join(str(d) for d in dirs))
    return sources, sorted(set(excluded))


def target_size(width: int, height: int, cap: int | None, patch: int) -> tuple[int, int]:
    """(width, height) after scaling the long side down to ``cap`` without the short side going below ``patch``
    (and never up)."""
    scale = 1.0 if cap is None else min(1.0, cap / max(width, height))
    scale = min(1.0, max(scale, patch / min(width, height)))
    if scale >= 1.0:
        return width, height
    return max(1, round(width * scale)), max(1, round(height * scale))


def encode_jpeg(pixels: np.ndarray, size: tuple[int, int], quality: int) -> bytes:
    """HxWx3 uint8 → (Lanczos resize to ``size`` = (w, h) if needed) → baseline JPEG bytes (4:2:0)."""
    from PIL import Image

    image = Image.fromarray(pixels)
    if image.size != size:
        image = image.resize(size, Image.Resampling.LANCZOS)
    buffer = io.BytesIO()
    image.save(buffer, format="JPEG", quality=quality, subsampling=2, optimize=True, progressive=False)
    return buffer.getvalue()


def _origins(sources: list[PackSource]) -> dict[Path, dict]:
    """Provenance rows of ``MANIFEST.csv`` files beside the folders (``folder/file`` → source_repo, commit, path)."""
    rows: dict[Path, dict] = {}
    for parent in sorted({s.path.parent.parent for s in sources}):
        table = parent / "MANIFEST.csv"
        if not table.is_file():
            continue
        with open(table, newline="") as f:
            for row in csv.DictReader(f):
                if row.get("file"):
                    keep = {k: row[k] for k in ("source_repo", "commit", "source_path") if row.get(k)}
                    rows[(parent / row["file"]).resolve()] = keep
    return rows


class _Encoder:
    """Encodes sources at a long-side cap, caching every result in ``cache`` (restartable)."""

    def __init__(self, sources: list[PackSource], cache: Path, patch: int, quality: int):
        self.sources, self.cache, self.patch, self.quality = sources, cache, patch, quality
        self.sha = [sha256_file(s.path) for s in sources]
        self.dims: list[tuple[int, int] | None] = [None] * len(sources)
        cache.mkdir(parents=True, exist_ok=True)

    def _pixels(self, k: int) -> np.ndarray:
        pixels = to_uint8(read_image(self.sources[k].path))  # EXIF orientation applied, 16-bit/grey/alpha handled
        self.dims[k] = (pixels.shape[1], pixels.shape[0])
        return pixels

    def size_at(self, k: int, cap: int | None) -> tuple[int, int] | None:
        return None if self.dims[k] is None else target_size(*self.dims[k], cap, self.patch)

    def encode(self, k: int, cap: int | None) -> Path:
        size = self.size_at(k, cap)
        pixels = None
        if size is None:
            pixels = self._pixels(k)
            size = self.size_at(k, cap)
        path = self.cache / f"{self.sha[k][:24]}_{size[0]}x{size[1]}_q{self.quality}.jpg"
        if not path.is_file():
            data = encode_jpeg(self._pixels(k) if pixels is None else pixels, size, self.quality)
            write_bytes(path, data)
        return path

    def pixels_at(self, cap: int | None) -> int:
        return sum(w * h for w, h in (self.size_at(k, cap) for k in range(len(self.sources))))


def _file_names(sources: list[PackSource]) -> list[str]:
    """``<split>/<folder>/<stem>.jpg``, with the source suffix added to the stem where two stems collide."""
    stems: dict[tuple[str, str], int] = {}
    for s in sources:
        stems[(s.folder, s.path.stem)] = stems.get((s.folder, s.path.stem), 0) + 1
    out = []
    for s in sources:
        stem = s.path.stem if stems[(s.folder, s.path.stem)] == 1 else f"{s.path.stem}_{s.path.suffix.lstrip('.')}"
        out.append(f"{s.split}/{s.folder}/{stem}.jpg")
    return out


def _manifest(sources, encoder, files, names, cap, options, excluded, origins) -> dict:
    import PIL

    images = []
    for k, (s, path, name) in enumerate(zip(sources, files, names)):
        data = path.read_bytes()
        entry = {
            "file": name,
            "split": s.split,
            "folder": s.folder,
            "source": f"{s.folder}/{s.path.name}",
            "source_sha256": encoder.sha[k],
            "source_size": list(encoder.dims[k]),
            "size": list(encoder.size_at(k, cap)),
            "bytes": len(data),
            "sha256": hashlib.sha256(data).hexdigest(),
        }
        origin = origins.get(s.path.resolve())
        if origin:
            entry["origin"] = origin
        images.append(entry)
    counts = {split: sum(e["split"] == split for e in images) for split in ("train", "val")}
    return {
        "kind": KIND,
        "format": PACK_FORMAT,
        "options": options,
        "long_side_cap": cap,
        "encoder": f"Pillow {PIL.__version__}",
        "split_rule": {"test": list(TEST_FOLDERS), "val": list(VAL_FOLDERS), "train": "every other folder"},
        "excluded_test_folders": excluded,
        "counts": counts,
        "total_bytes": sum(e["bytes"] for e in images),
        "images": images,
    }


def _dump(manifest: dict) -> str:
    return json.dumps(manifest, indent=1, sort_keys=True) + "\n"


def make_pack(
    clean: Sequence[str | os.PathLike],
    out: str | os.PathLike,
    max_mib: float = 40.0,
    patch: int = 256,
    quality: int = 90,
    max_side: int | None = None,
    progress: bool = False,
) -> dict:
    """Write a training pack of the train and validation images in ``clean`` to ``out``.

    Args:
        clean: folders of clean images, or parent folders of such folders (test folders are left out there;
            a test folder given directly is an error).
        out: the pack folder (replaced atomically if it holds an older pack; anything else there is an error).
        max_mib: size limit of the whole pack (files + manifest), MiB.
        patch: the downscale never brings an image's short side below this (the training crop size).
        quality: JPEG quality (1–100).
        max_side: largest long-side cap to try (default: full resolution first).
        progress: show a progress bar per encoding pass.

    Returns:
        A summary: ``out``, ``images`` per split, ``bytes``, ``long_side_cap``, ``excluded_test_folders``,
        ``up_to_date`` (True when ``out`` already held this exact pack).
    """
    out = Path(out)
    if not 1 <= quality <= 100:
        raise D2TurbError(f"quality must be between 1 and 100, got {quality}", param="quality")
    if patch < 16:
        raise D2TurbError(f"patch must be at least 16, got {patch}", param="patch")
    if not (isinstance(max_mib, (int, float)) and math.isfinite(max_mib) and 0 < max_mib <= MAX_MIB):
        raise D2TurbError(
            f"max_mib must be a number above 0 and at most {MAX_MIB} (1 TiB), got {max_mib}", param="max_mib"
        )
    if max_side is not None and not (isinstance(max_side, int) and patch <= max_side <= 65535):
        raise D2TurbError(
            f"max_side must be an integer from patch ({patch}) to 65535, got {max_side}", param="max_side"
        )
    if out.exists() and not (out / MANIFEST).is_file() and (not out.is_dir() or any(out.iterdir())):
        raise D2TurbError(f"{out}: exists and is not a d2turb pack; choose another --out")
    sources, excluded = collect_sources(clean)
    options = {"max_mib": max_mib, "patch": patch, "quality": quality, "max_side": max_side, "subsampling": "4:2:0"}
    staging = out.parent / f".{out.name}.partial"
    encoder = _Encoder(sources, staging / "cache", patch, quality)
    fingerprint = [[f"{s.folder}/{s.path.name}", sha] for s, sha in zip(sources, encoder.sha)]
    if (out / MANIFEST).is_file():
        try:
            previous = read_pack(out, verify=True)  # intact (every checksum) and ...
            same = previous.get("options") == options and previous.get("excluded_test_folders") == excluded
            same = same and [[e["source"], e["source_sha256"]] for e in previous["images"]] == fingerprint
        except (D2TurbError, KeyError, TypeError):
            same = False
        if same:  # ... made from the same sources with the same options: nothing to do
            shutil.rmtree(staging, ignore_errors=True)
            return _summary(out, previous, up_to_date=True)
    rungs = [r for r in LADDER if max_side is None or (r is not None and r <= max_side)]
    if max_side is not None and max_side not in rungs:
        rungs.insert(0, max_side)
    limit = int(max_mib * _MIB)
    names, origins = _file_names(sources), _origins(sources)
    i, manifest, files, cap = 0, None, [], None
    while i < len(rungs):
        cap = rungs[i]
        files = _encode_all(encoder, cap, progress, f"pack (long side ≤ {cap or 'full'})")
        manifest = _manifest(sources, encoder, files, names, cap, options, excluded, origins)
        used = manifest["total_bytes"] + len(_dump(manifest).encode())
        if used <= limit:
            break
        # bytes ∝ pixels predicts the next rung that may fit (it under-estimates, so go on from there if not)
        per_pixel = manifest["total_bytes"] / encoder.pixels_at(cap)
        j = i + 1
        while j < len(rungs) - 1 and per_pixel * encoder.pixels_at(rungs[j]) > 0.97 * (
            limit - (used - manifest["total_bytes"])
        ):
            j += 1
        i = j
    else:
        raise D2TurbError(
            f"the pack does not fit in {max_mib} MiB even with the long side at {rungs[-1]} px "
            f"({used / _MIB:.1f} MiB); raise --max-mib or lower --quality"
        )
    build = staging / "pack"
    shutil.rmtree(build, ignore_errors=True)
    for path, name in zip(files, names):
        target = build / name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, target)
    write_text(build / MANIFEST, _dump(manifest))
    if out.exists():
        shutil.rmtree(staging / "old", ignore_errors=True)
        os.replace(out, staging / "old")
    os.replace(build, out)
    shutil.rmtree(staging, ignore_errors=True)
    return _summary(out, manifest, up_to_date=False)


def _encode_all(encoder: _Encoder, cap: int | None, progress: bool, desc: str) -> list[Path]:
    indices = range(len(encoder.sources))
    if progress:
        from tqdm import tqdm

        indices = tqdm(indices, desc=desc, dynamic_ncols=True)
    return [encoder.encode(k, cap) for k in indices]


def _summary(out: Path, manifest: dict, up_to_date: bool) -> dict:
    return {
        "out": str(out),
        "images": manifest["counts"],
        "bytes": manifest["total_bytes"] + len(_dump(manifest).encode()),
        "long_side_cap": manifest["long_side_cap"],
        "excluded_test_folders": manifest["excluded_test_folders"],
        "up_to_date": up_to_date,
    }
