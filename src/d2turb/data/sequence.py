"""Sequence datasets: ``make-dataset --frames N`` writes turbulent clips of a still crop (frozen-flow
turbulence, d2turb.sim.sequence), with the same restartable, sharded machinery as pairs.

A sequence sample keeps the five files of a pair, so every resume / merge / check rule of the pair
layout applies unchanged; the frames are stacked vertically ("filmstrip"):

    turb/<id>.png    8-bit RGB, (N·H) × W: frame f is rows f·H … (f+1)·H − 1
    tilt/<id>.png    same, tilt only
    gt/<id>.png      the clean crop (H × W), the same scene for every frame
    bwd_flow_px/<id>.npy  float16 (N, 2, H, W) backward flow per frame: warp(tilt_f, bwd_flow_px_f) ≈ gt
                     (``flow/<id>.npy`` in datasets of the earlier layout, still read)
    depth/<id>.png   16-bit depth of the crop (H × W)

``dataset.json`` records ``frames`` and ``sequence`` (fps, wind, wind_dir, boil). Field-realistic clips
(``--profile field``, d2turb.data.field) store ``gt`` as a filmstrip too: the truth of every frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from d2turb.data.layout import Sample, file_path, load_flow, open_split, read_meta, record_entries
from d2turb.errors import D2TurbError
from d2turb.io import read_image
from d2turb.ops.splat import invert_flow
from d2turb.sim.sequence import check_sequence_args, wind_speeds

SEQUENCE_DEFAULTS = {"fps": 30.0, "wind": 1.0, "wind_dir": 0.0, "boil": 0.0}


def sequence_settings(frames: int, sequence: dict) -> dict:
    """Checked sequence settings (fps, wind m/s or list from aperture to object, wind_dir deg, boil)."""
    if not isinstance(frames, int) or frames < 1:
        raise D2TurbError(f"frames must be a positive integer, got {frames!r}", param="frames")
    unknown = sorted(set(sequence) - set(SEQUENCE_DEFAULTS))
    if unknown:
        raise D2TurbError(f"unknown sequence setting {unknown[0]!r}; choose from {', '.join(SEQUENCE_DEFAULTS)}")
    out = {**SEQUENCE_DEFAULTS, **sequence}
    check_sequence_args(frames, out["fps"], out["wind_dir"], out["boil"])
    wind = out["wind"]
    wind = [float(v) for v in wind] if isinstance(wind, (list, tuple)) else float(wind)
    wind_speeds(wind, np.linspace(0, 1, 3))
    return {"fps": float(out["fps"]), "wind": wind, "wind_dir": float(out["wind_dir"]), "boil": float(out["boil"])}


def simulate_sequence_chunk(sim, clean, depth, dr0, generator, frames: int, settings: dict):
    """One chunk of sequence samples: (turb (B,3,N·H,W), tilt (B,3,N·H,W), bwd_flow_px (B,N,2,H,W)) on the CPU:
    the backward flow of each frame, as for pairs."""
    turb, tilt, bwd_flow_px = [], [], []
    for res in sim.sequence(clean, frames=frames, depth=depth, dr0=dr0, generator=generator, **settings):
        turb.append(res.turb.float().cpu())
        tilt.append(res.tilt.float().cpu())
        bwd_flow_px.append(invert_flow(res.fwd_flow_px).float().cpu())
    return torch.cat(turb, -2), torch.cat(tilt, -2), torch.stack(bwd_flow_px, 1)


class SequenceDataset(Dataset):
    """Sequences written by ``d2turb make-dataset --frames N`` in ``root`` (or ``root/<split>``).

    Item: dict(turb, tilt (N,3,H,W) float32 in [0,1]; gt (3,H,W), or (N,3,H,W) the truth of each frame in a field
    dataset (``make-dataset --profile field``), which also gives ``boxes``: (N, K, 4) int64 [x0, y0, x1, y1] of its K
    moving objects per frame (end exclusive; −1 where the object is outside the frame); bwd_flow_px (N,2,H,W) float32
    px backward flow per frame (and ``flow``, its deprecated name); depth (1,H,W); dr0 float32 scalar; bin int64
    scalar; id str).
    ``frames`` = a random window of that many consecutive frames (default: all).
    """

    def __init__(self, root: str | Path, split: str | None = None, frames: int | None = None):
        self.root, config = open_split(root, split)
        self.frames = int(config.get("frames", 1))
        if self.frames < 2:
            raise D2TurbError(f"{self.root}: not a sequence dataset (made without --frames); use PairDataset")
        if frames is not None and not 1 <= frames <= self.frames:
            raise D2TurbError(f"frames {frames} must be between 1 and the dataset's {self.frames}")
        self.window = frames or self.frames
        self.patch = int(config["patch"])
        self.field = config.get("profile") == "field"
        self.records = sorted(read_meta(self.root), key=lambda r: r["index"])

    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, index: int) -> dict:
        rec = self.records[index]
        sid, n, p = rec["id"], self.frames, self.patch
        f0 = int(torch.randint(0, n - self.window + 1, ())) if self.window < n else 0
        sl = slice(f0, f0 + self.window)
        bwd_flow_px = torch.from_numpy(load_flow(file_path(self.root, "bwd_flow_px", sid))[sl].astype(np.float32))
        gt = read_image(file_path(self.root, "gt", sid))
        extra = {}
        if self.field:
            gt = gt.view(3, n, p, p).transpose(0, 1)[sl].contiguous()
            extra["boxes"] = field_boxes(rec, n)[sl]
        return Sample(
            {
                **extra,
                "turb": read_image(file_path(self.root, "turb", sid)).view(3, n, p, p).transpose(0, 1)[sl].contiguous(),
                "tilt": read_image(file_path(self.root, "tilt", sid)).view(3, n, p, p).transpose(0, 1)[sl].contiguous(),
                "gt": gt,
                "bwd_flow_px": bwd_flow_px,
                **record_entries(self.root, rec),
            }
        )


def field_boxes(record: dict, frames: int) -> torch.Tensor:
    """(N, K, 4) int64 boxes [x0, y0, x1, y1] (end exclusive) of a field clip's K moving objects per frame, from its
    meta line; −1 where an object is outside the frame."""
    objects = record.get("field", {}).get("objects", [])
    out = torch.full((frames, len(objects), 4), -1, dtype=torch.int64)
    for k, obj in enumerate(objects):
        for t, box in enumerate(obj.get("boxes", [])[:frames]):
            if box is not None:
                out[t, k] = torch.tensor(box)
    return out
