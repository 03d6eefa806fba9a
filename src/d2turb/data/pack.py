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
:class:`PackCrops` decodes a pack once into memory (uint8, on the training device) and serves random crops.
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
import torch
from torch.utils.data import Dataset

from d2turb.data.generate import make_depth_fn, resize_up
from d2turb.data.layout import inside
from d2turb.data.split import SPLITS, TEST_FOLDERS, VAL_FOLDERS, split_of
from d2turb.errors import D2TurbError
from d2turb.io import list_images, read_image, to_uint8, write_bytes, write_text

PACK_FORMAT = 1
MANIFEST = "pack.json"
MAX_MIB = 1 << 20  # --max-mib at most 1 TiB
KIND = "d2turb-pack"
LADDER: tuple[int | None, ...] = (None, 1024, 896, 768, 704, 640, 576, 512, 480, 448, 416, 384, 352, 320, 288, 256)
_MIB = 1 << 20


@dataclass(frozen=True)
class PackSource:
    """One clean image going into a pack."""

    path: Path
    folder: str  # the folder's name: decides the split
    split: str


def _sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                digest.update(chunk)
    except OSError as exc:  # unreadable, a dangling or looping link
        raise D2TurbError(f"{path}: cannot read ({exc.strerror or exc.__class__.__name__})") from exc
    return digest.hexdigest()


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
        self.sha = [_sha256_file(s.path) for s in sources]
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


def read_pack(pack: str | os.PathLike, verify: bool = True) -> dict:
    """The manifest of a pack, checked: format, no test images, and (``verify``) every file's SHA-256.

    Raises:
        D2TurbError: not a pack, a test image inside, a missing or modified file.
    """
    pack = Path(pack)
    path = pack / MANIFEST
    if not path.is_file():
        raise D2TurbError(f"{pack}: not a d2turb pack (no {MANIFEST}); make one with `d2turb make-pack`")
    try:
        manifest = json.loads(path.read_text())
        images = manifest["images"]
        ok = manifest.get("kind") == KIND and isinstance(images, list)
    except (ValueError, KeyError, TypeError):
        ok = False
    if not ok:
        raise D2TurbError(f"{path}: not a valid pack manifest")
    if manifest.get("format") != PACK_FORMAT:
        raise D2TurbError(f"{path}: pack format {manifest.get('format')!r}, this d2turb reads {PACK_FORMAT}")
    for entry in images:
        if not isinstance(entry, dict):
            raise D2TurbError(f"{path}: not a valid pack manifest (an image entry is {json.dumps(entry)[:60]})")
        inside(pack, entry.get("file"), str(path))  # every file the manifest names lies inside the pack
        if entry.get("split") not in SPLITS or entry["split"] == "test" or split_of(entry.get("folder", "")) == "test":
            raise D2TurbError(f"{pack}: holds a test image ({entry.get('file')}); packs are for training only")
        if verify:
            file = pack / entry["file"]
            if not file.is_file():
                raise D2TurbError(f"{pack}: missing file {entry['file']}")
            if _sha256_file(file) != entry["sha256"]:
                raise D2TurbError(f"{pack}: {entry['file']} does not match its checksum in {MANIFEST}")
    return manifest


def _decode(path: Path) -> torch.Tensor:
    from PIL import Image

    with Image.open(path) as image:
        pixels = np.asarray(image.convert("RGB"), dtype=np.uint8)
    return torch.from_numpy(pixels.copy()).permute(2, 0, 1).contiguous()


def _resize_up_uint8(image: torch.Tensor, patch: int) -> torch.Tensor:
    if min(image.shape[-2:]) >= patch:
        return image
    return (resize_up(image.float() / 255.0, patch) * 255.0).round().to(torch.uint8)


def decode_pack(
    pack: str | os.PathLike,
    split: str = "train",
    patch: int = 256,
    device: str | torch.device = "cpu",
    depth: str = "prior",
    verify: bool = True,
) -> tuple[list[torch.Tensor], list[torch.Tensor] | None, list[str]]:
    """Decode a pack's ``split`` images once into memory.

    Args:
        pack: pack folder.
        split: ``train`` or ``val``.
        patch: images with a short side below it are resized up (bilinear, as make-dataset does).
        device: where the tensors live (the training device).
        depth: ``none`` | ``prior`` | DIR | ``anything:PATH`` (see ``d2turb.depth.depth_for_image``), computed once
            per image on the decoded image.
        verify: check the files' checksums first.

    Returns:
        (images: uint8 (3, H, W) each, depths: float16 (1, H, W) each in [0, 1] or None for ``none``,
        names: ``folder/stem`` each).
    """
    if split not in ("train", "val"):
        raise D2TurbError(f"a pack has train and val images, not {split!r}")
    pack = Path(pack)
    entries = [e for e in read_pack(pack, verify=verify)["images"] if e["split"] == split]
    if not entries:
        raise D2TurbError(f"{pack}: no {split} images")
    device = torch.device(device)
    depth_fn = make_depth_fn(depth, device=device)
    images, depths, names = [], [], []
    for entry in entries:
        image = _resize_up_uint8(_decode(pack / entry["file"]), patch)
        if depth_fn is not None:
            d = depth_fn(image.float() / 255.0, pack / entry["file"]).reshape(1, *image.shape[-2:])
            depths.append(d.to(device=device, dtype=torch.float16))
        images.append(image.to(device))
        names.append(f"{entry['folder']}/{Path(entry['file']).stem}")
    return images, (depths if depth_fn is not None else None), names


class PackCrops(Dataset):
    """Random ``patch``² crops (+ flips) of a pack's images, decoded once into memory on ``device``.

    Item ``i`` uses image ``i mod n`` and a fresh random crop from the dataset's own CPU ``generator`` (no global
    RNG, no decoding per item): dict(gt float32 (3, p, p) in [0, 1], depth float32 (1, p, p) (ones for
    ``depth="none"``), id ``folder/stem@x0,y0``), all on ``device``. Use it with ``num_workers=0``.

    Args:
        pack: pack folder made by :func:`make_pack`.
        patch: crop size.
        split: ``train`` (default) or ``val``.
        length: items per epoch (default: one per image).
        hflip, vflip: random mirroring.
        depth: depth spec (see :func:`decode_pack`).
        device: training device.
        seed: seed of :attr:`generator` (its state is part of a training checkpoint).
    """

    def __init__(
        self,
        pack: str | os.PathLike,
        patch: int = 256,
        split: str = "train",
        length: int | None = None,
        hflip: bool = True,
        vflip: bool = False,
        depth: str = "prior",
        device: str | torch.device = "cpu",
        seed: int = 0,
    ):
        if patch < 16:
            raise D2TurbError(f"patch must be at least 16 px, got {patch}")
        self.images, self.depths, self.names = decode_pack(pack, split, patch, device, depth)
        self.patch, self.hflip, self.vflip = patch, hflip, vflip
        self.length = len(self.images) if length is None else int(length)
        self.generator = torch.Generator().manual_seed(seed)

    def __len__(self) -> int:
        return self.length

    def _coin(self) -> bool:
        return bool(torch.rand((), generator=self.generator) < 0.5)

    def __getitem__(self, index: int) -> dict:
        k = index % len(self.images)
        image, p = self.images[k], self.patch
        h, w = image.shape[-2:]
        y0 = int(torch.randint(0, h - p + 1, (), generator=self.generator))
        x0 = int(torch.randint(0, w - p + 1, (), generator=self.generator))
        gt = image[:, y0 : y0 + p, x0 : x0 + p].float() / 255.0
        if self.depths is None:
            depth = torch.ones_like(gt[:1])
        else:
            depth = self.depths[k][:, y0 : y0 + p, x0 : x0 + p].float()
        if self.hflip and self._coin():
            gt, depth = gt.flip(-1), depth.flip(-1)
        if self.vflip and self._coin():
            gt, depth = gt.flip(-2), depth.flip(-2)
        return {"gt": gt.contiguous(), "depth": depth.contiguous(), "id": f"{self.names[k]}@{x0},{y0}"}

    def center_crops(self, size: int | None = None) -> list[dict]:
        """One deterministic centre crop per image (validation): dict(gt (3,s,s), depth (1,s,s), id)."""
        size = size or self.patch
        out = []
        for k, image in enumerate(self.images):
            h, w = image.shape[-2:]
            s = min(size, h, w)
            y0, x0 = (h - s) // 2, (w - s) // 2
            gt = image[:, y0 : y0 + s, x0 : x0 + s].float() / 255.0
            depth = torch.ones_like(gt[:1]) if self.depths is None else self.depths[k][:, y0 : y0 + s, x0 : x0 + s]
            out.append({"gt": gt, "depth": depth.float(), "id": self.names[k]})
        return out
