"""Reading a training pack (:mod:`~d2turb.data.pack` makes them): the manifest, checked (:func:`read_pack`), the
images decoded once into memory (:func:`decode_pack`) and the random crops training draws from them
(:class:`PackCrops`)."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from d2turb.data.layout import inside
from d2turb.data.sources import make_depth_fn, resize_up
from d2turb.data.split import SPLITS, split_of
from d2turb.errors import D2TurbError

PACK_FORMAT = 1
MANIFEST = "pack.json"
KIND = "d2turb-pack"


def sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                digest.update(chunk)
    except OSError as exc:  # unreadable, a dangling or looping link
        raise D2TurbError(f"{path}: cannot read ({exc.strerror or exc.__class__.__name__})") from exc
    return digest.hexdigest()


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
            if sha256_file(file) != entry["sha256"]:
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
