"""PyTorch datasets: generated pairs from disk, and clean crops + on-the-fly synthesis on the training device.

Samples hold the backward flow V as ``bwd_flow_px``: (…, 2, H, W) in pixels, x then y, ``warp(tilt, bwd_flow_px) ≈
gt`` (the files' ``bwd_flow_px/<id>.npy``, ``flow/<id>.npy`` in datasets of the earlier layout). Samples are
:class:`~d2turb.data.layout.Sample` dicts: ``flow``, the deprecated name, still reads ``bwd_flow_px`` (warning once)."""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path

import torch
from torch.utils.data import Dataset

from d2turb.data.layout import Sample, bin_index, file_path, load_flow, open_split, read_meta, record_entries
from d2turb.data.sources import make_depth_fn, resize_up
from d2turb.errors import D2TurbError
from d2turb.io import expand_inputs, read_image
from d2turb.ops.checks import check_shape
from d2turb.ops.splat import invert_flow
from d2turb.sim.params import BINS, bin_spans, dr0_bin, dr0_from_uniform

FLOW_KEYS = ("bwd_flow_px", "flow")  # the backward flow of a sample, and its deprecated name


def _with_flow(sample: dict, out: dict, change) -> dict:
    """``out`` with ``change`` applied to the sample's backward flow, under each of its names the sample stores (a
    plain dict of an earlier version may hold it as ``flow``)."""
    stored = [k for k in FLOW_KEYS if dict.get(sample, k) is not None]
    if stored:
        bwd_flow_px = change(dict.__getitem__(sample, stored[0]))
        out.update({k: bwd_flow_px for k in stored})
    return out


def _copy(sample: dict) -> dict:
    """A shallow copy of the same kind (a :class:`Sample` stays one)."""
    return type(sample)(sample) if isinstance(sample, Sample) else dict(sample)


def flip_sample(sample: dict, horizontal: bool = True) -> dict:
    """Mirror every image-like entry; the backward flow's matching component changes sign
    (mirroring x → W-1-x turns a displacement +v into -v)."""
    dim, comp = (-1, 0) if horizontal else (-2, 1)
    out = _copy(sample)
    for key in ("turb", "tilt", "gt", "depth"):
        if key in out and out[key] is not None:
            out[key] = out[key].flip(dim)

    def flip(bwd_flow_px):
        bwd_flow_px = bwd_flow_px.flip(dim)
        bwd_flow_px[..., comp, :, :] = -bwd_flow_px[..., comp, :, :]
        return bwd_flow_px

    return _with_flow(sample, out, flip)


def crop_sample(sample: dict, y0: int, x0: int, size: int) -> dict:
    """Crop every image-like entry; flow is in pixels, so its values stay valid after a crop."""
    out = _copy(sample)
    for key in ("turb", "tilt", "gt", "depth"):
        if key in out and out[key] is not None:
            out[key] = out[key][..., y0 : y0 + size, x0 : x0 + size]
    return _with_flow(sample, out, lambda bwd_flow_px: bwd_flow_px[..., y0 : y0 + size, x0 : x0 + size])


class PairDataset(Dataset):
    """Pairs written by ``d2turb make-dataset`` in ``root`` (or ``root/<split>``); ``split`` must match the data's.

    Item: dict(turb, tilt, gt (3,H,W) float32 in [0,1]; bwd_flow_px (2,H,W) float32 px backward flow (and ``flow``,
    its deprecated name); depth (1,H,W) in [0,1]; dr0 float32 scalar; bin int64 scalar (index into
    ("weak","medium","strong")); id str). ``crop`` = random crop size, ``hflip``/``vflip`` = random mirroring (flow
    kept consistent). ``skip_invalid``: meta lines that are not valid records are left out (their messages in
    ``invalid``) instead of refusing the dataset.
    Augmentation randomness comes from ``torch``'s global RNG (seeded per DataLoader worker).
    """

    def __init__(
        self,
        root: str | Path,
        split: str | None = None,
        crop: int | None = None,
        hflip: bool = False,
        vflip: bool = False,
        skip_invalid: bool = False,
    ):
        self.root, config = open_split(root, split)
        if int(config.get("frames", 1)) > 1:
            raise D2TurbError(f"{self.root}: holds sequences (make-dataset --frames); use d2turb.data.SequenceDataset")
        self.invalid: list[str] = []  # with skip_invalid: one message per meta line that is not a valid record
        self.records = sorted(read_meta(self.root, self.invalid if skip_invalid else None), key=lambda r: r["index"])
        self.patch = int(config["patch"])
        if crop is not None and not 1 <= crop <= self.patch:
            raise D2TurbError(f"crop {crop} must be between 1 and the dataset patch size {self.patch}")
        self.crop, self.hflip, self.vflip = crop, hflip, vflip

    def __len__(self) -> int:
        return len(self.records)

    def load(self, index: int) -> dict:
        """The files of sample ``index``; one of the wrong shape is a ``D2TurbError`` naming it (a loader that
        skips bad samples, as evaluate does, skips it)."""
        rec = self.records[index]
        sid = rec["id"]
        bwd_flow_px = torch.from_numpy(load_flow(file_path(self.root, "bwd_flow_px", sid)))
        sample = Sample(
            {
                "turb": read_image(file_path(self.root, "turb", sid)),
                "tilt": read_image(file_path(self.root, "tilt", sid)),
                "gt": read_image(file_path(self.root, "gt", sid)),
                "bwd_flow_px": bwd_flow_px,
                **record_entries(self.root, rec),
            }
        )
        h, w = sample["gt"].shape[-2:]
        for kind, key, channels in (
            ("turb", "turb", 3),
            ("tilt", "tilt", 3),
            ("bwd_flow_px", "bwd_flow_px", 2),
            ("depth", "depth", 1),
        ):
            if tuple(sample[key].shape) != (channels, h, w):
                raise D2TurbError(
                    f"{file_path(self.root, kind, sid)}: {kind} has shape {tuple(sample[key].shape)}, expected "
                    f"({channels}, {h}, {w}) like gt/{sid}.png"
                )
        return sample

    def __getitem__(self, index: int) -> dict:
        sample = self.load(index)
        if self.crop is not None and self.crop < self.patch:
            h, w = sample["gt"].shape[-2:]
            y0 = int(torch.randint(0, h - self.crop + 1, ()))
            x0 = int(torch.randint(0, w - self.crop + 1, ()))
            sample = crop_sample(sample, y0, x0, self.crop)
        if self.hflip and torch.rand(()) < 0.5:
            sample = flip_sample(sample, horizontal=True)
        if self.vflip and torch.rand(()) < 0.5:
            sample = flip_sample(sample, horizontal=False)
        return sample


class CleanCropDataset(Dataset):
    """Random ``patch``² crops of clean images with their depth (computed on the full image, then
    cropped the same way), for on-the-fly synthesis. Item: dict(gt (3,p,p), depth (1,p,p), id str).

    ``length`` items per epoch (default: one per image); item i uses image i % n_images and a fresh
    random crop (torch global RNG). Images smaller than the patch are resized up, as in make-dataset.
    Images and their full-image depth maps are cached per worker (``cache`` entries; None = all).
    """

    def __init__(
        self,
        dirs: list[str | Path],
        patch: int = 256,
        depth_spec: str = "prior",
        length: int | None = None,
        hflip: bool = True,
        cache: int | None = None,
    ):
        self.paths = expand_inputs([str(d) for d in dirs])
        if patch < 16:
            raise D2TurbError(f"patch must be at least 16 px, got {patch}")
        self.patch, self.depth_spec, self.hflip = patch, depth_spec, hflip
        self.length = len(self.paths) if length is None else int(length)
        self.depth_fn = make_depth_fn(depth_spec)
        self.cache_size = cache
        self._cache: OrderedDict[int, tuple] = OrderedDict()

    def __len__(self) -> int:
        return self.length

    def _load(self, k: int):
        if k in self._cache:
            self._cache.move_to_end(k)
            return self._cache[k]
        image = read_image(self.paths[k])
        if self.depth_fn is None:
            depth = torch.ones(1, *image.shape[-2:])
        else:
            depth = self.depth_fn(image, self.paths[k]).float().reshape(1, *image.shape[-2:])
        item = (resize_up(image, self.patch), resize_up(depth, self.patch))
        self._cache[k] = item
        if self.cache_size is not None and len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)
        return item

    def __getitem__(self, index: int) -> dict:
        k = index % len(self.paths)
        image, depth = self._load(k)
        h, w = image.shape[-2:]
        y0 = int(torch.randint(0, h - self.patch + 1, ()))
        x0 = int(torch.randint(0, w - self.patch + 1, ()))
        sample = crop_sample({"gt": image, "depth": depth}, y0, x0, self.patch)
        if self.hflip and torch.rand(()) < 0.5:
            sample = flip_sample(sample)
        sample = {key: v.contiguous() for key, v in sample.items()}
        sample["id"] = f"{self.paths[k].stem}@{x0},{y0}"
        return sample


class OnTheFlySynthesis:
    """Applied to a collated CleanCropDataset batch on the training device: draws D/r0 uniformly over the union of
    ``bins`` per sample and one imaging geometry per batch (``simulator`` is one Simulator or a list, e.g. one per
    geometry of :func:`d2turb.sim.geometry.geometry_bank`), runs the simulator batched (new turbulence on every call)
    and returns the same dict as PairDataset, with ``bwd_flow_px`` (and ``flow``) the backward flow of the simulator's
    forward flow.
    """

    def __init__(
        self,
        simulator,
        bins=tuple(BINS),
        device: str | torch.device = "cpu",
        seed: int | None = None,
        use_depth: bool = True,
    ):
        self.spans = bin_spans(bins)
        self.simulators = list(simulator) if isinstance(simulator, (list, tuple)) else [simulator]
        if not self.simulators:
            raise D2TurbError("OnTheFlySynthesis needs at least one simulator")
        self.bins = tuple(bins)
        self.device = torch.device(device)
        self.use_depth = use_depth
        self.generator = torch.Generator(device=self.device)
        if seed is None:
            self.generator.seed()
        else:
            self.generator.manual_seed(seed)

    @property
    def simulator(self):
        return self.simulators[0]

    def _uniform(self, n: int) -> torch.Tensor:
        return torch.rand(n, generator=self.generator, device=self.device, dtype=torch.float64).cpu()

    def sample_dr0(self, n: int) -> torch.Tensor:
        """n values uniform over the union of the bins (as in the train split of make-dataset)."""
        return torch.from_numpy(dr0_from_uniform(self._uniform(n).numpy(), self.spans)).float()

    def __call__(self, batch: dict) -> dict:
        gt = batch["gt"].to(self.device, non_blocking=True)
        check_shape(gt, "B 3 H W", "batch of clean images")
        depth = batch.get("depth")
        depth = depth.to(self.device, non_blocking=True) if (depth is not None and self.use_depth) else None
        dr0 = self.sample_dr0(gt.shape[0])
        g = (
            min(int(self._uniform(1)[0] * len(self.simulators)), len(self.simulators) - 1)
            if len(self.simulators) > 1
            else 0
        )
        with torch.no_grad():
            res = self.simulators[g](gt, depth=depth, dr0=dr0.to(self.device), generator=self.generator)
            bwd_flow_px = invert_flow(res.fwd_flow_px)
        return Sample(
            {
                "turb": res.turb,
                "tilt": res.tilt,
                "gt": gt,
                "bwd_flow_px": bwd_flow_px,
                "depth": depth if depth is not None else torch.ones_like(gt[:, :1]),
                "dr0": dr0.to(self.device),
                "bin": torch.tensor([bin_index(dr0_bin(float(v))) for v in dr0], device=self.device),
                "geometry": torch.full((gt.shape[0],), g, device=self.device),
                "id": batch.get("id"),
            }
        )
