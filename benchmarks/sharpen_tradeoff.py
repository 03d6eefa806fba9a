"""Sharpening after a shipped model: what it costs on validation and what it buys on the real frames (issue 24).

    PYTHONPATH=src python3 benchmarks/sharpen_tradeoff.py --val VAL_DIR [--real ../shared/data/real]
        [--weights nafnet-cpu-spectral] [--usm 0.7:0.25 1.0:0.25 ...] [--json FILE]

The model restores every pair of the synthetic validation set VAL_DIR (``make-dataset``, e.g. ``val_field`` of
docs/training.md) and every real frame NIQE can score (the PNGs under ``--real``, as MODEL_CARD.md counts them);
each output is then sharpened by an unsharp mask, ``y + amount·(y − G_σ * y)`` (``cv2.GaussianBlur``, σ in px), for
each ``σ:amount`` given (``0:0`` = the model alone, always included). Per setting: PSNR and SSIM of the 8-bit output
per bin (as ``d2turb evaluate`` computes them), NIQE of the validation outputs, and NIQE of the real outputs (mean,
the airport clip, the other frames). Prints and writes one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
from pathlib import Path

import cv2
import numpy as np
import torch

from d2turb.data.datasets import PairDataset
from d2turb.errors import D2TurbError
from d2turb.eval.metrics import psnr, quantise_8bit, ssim
from d2turb.eval.niqe import niqe
from d2turb.io import read_image
from d2turb.restore.single import Restorer

BINS = ("weak", "medium", "strong")
ROOT = Path(__file__).resolve().parents[1]


def unsharp(image: torch.Tensor, sigma: float, amount: float) -> torch.Tensor:
    """``image + amount·(image − G_σ * image)`` clamped to [0, 1]; (3,H,W) float32."""
    if amount == 0:
        return image
    hwc = np.ascontiguousarray(image.permute(1, 2, 0).numpy())
    low = cv2.GaussianBlur(hwc, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    return torch.from_numpy(hwc + amount * (hwc - low)).permute(2, 0, 1).clamp(0, 1)


def _real_frames(folder: Path) -> list[tuple[str, torch.Tensor]]:
    frames = []
    for f in sorted(folder.rglob("*.png")):
        x = read_image(f)
        try:
            niqe(x)
        except D2TurbError:  # too few textured blocks (the 140² text frames)
            continue
        frames.append((str(f.relative_to(folder)), x))
    return frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--val", type=Path, required=True)
    ap.add_argument("--real", type=Path, default=ROOT.parent / "shared" / "data" / "real")
    ap.add_argument("--weights", default="nafnet-cpu-spectral")
    ap.add_argument("--usm", nargs="+", default=["0.7:0.25", "0.7:0.5", "1.0:0.25", "1.0:0.5"])
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    settings = [(0.0, 0.0)] + [tuple(float(v) for v in s.split(":")) for s in args.usm]
    restorer = Restorer(args.weights)
    val = PairDataset(args.val)
    items = [val[i] for i in range(len(val))]
    val_out = [restorer.restore(it["turb"]).clamp(0, 1) for it in items]
    real = _real_frames(args.real)
    real_out = [(name, restorer.restore(x).clamp(0, 1)) for name, x in real]
    result = {
        "settings": {"val": str(args.val), "real": str(args.real), "weights": args.weights, "usm": args.usm},
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "input": {},
        "rows": [],
    }
    rows = [("input", 0.0, 0.0, [it["turb"] for it in items], real)] + [
        (args.weights, s, a, [unsharp(y, s, a) for y in val_out], [(n, unsharp(y, s, a)) for n, y in real_out])
        for s, a in settings
    ]
    for name, sigma, amount, outs, reals in rows:
        per_bin = {b: [] for b in BINS}
        for it, y in zip(items, outs):
            y = quantise_8bit(y)
            per_bin[BINS[int(it["bin"])]].append((float(psnr(y, it["gt"])), float(ssim(y, it["gt"]))))
        real_niqe = {n: float(niqe(quantise_8bit(y))) for n, y in reals}
        airport = [v for n, v in real_niqe.items() if n.startswith("airport")]
        other = [v for n, v in real_niqe.items() if not n.startswith("airport")]
        row = {
            "model": name,
            "sigma_px": sigma,
            "amount": amount,
            "psnr": {b: round(float(np.mean([v[0] for v in per_bin[b]])), 3) for b in BINS},
            "ssim": {b: round(float(np.mean([v[1] for v in per_bin[b]])), 4) for b in BINS},
            "val_niqe": round(float(np.mean([float(niqe(quantise_8bit(y))) for y in outs])), 3),
            "real_niqe": {
                "mean": round(float(np.mean(list(real_niqe.values()))), 3),
                "airport": round(float(np.mean(airport)), 3) if airport else None,
                "other": round(float(np.mean(other)), 3) if other else None,
                "frames": len(real_niqe),
            },
        }
        result["rows"].append(row)
        print(json.dumps(row), flush=True)
    text = json.dumps(result, indent=1)
    if args.json:
        args.json.write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
