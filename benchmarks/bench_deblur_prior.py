"""The Wiener filter's prior after fusion, and whether the sharpest fusion holds anything the deconvolved mean lacks
(issue 40; docs/clips.md, "The Wiener filter's prior").

    PYTHONPATH=src python3 benchmarks/bench_deblur_prior.py --clips val_clips [--json FILE]

For each clip of a sequence dataset (``make-dataset --frames N``), ``ClipRestorer`` (window 32, DIS fast, 2 passes,
``--deblur none``) fuses it with the mean and with the sharpest fusion; every 4th output is kept. Then, per D/r0 bin,
PSNR with the global offset removed (``bench_fusion_peer.psnr_offset_removed``) and plain PSNR (8 px border cropped):

1. **Prior scan**: the physics Wiener filter at the clip's true D/r0, optics and depth modulation with the Laplacian
   prior (|L|² ≈ (2πf)⁴) and the gradient prior (|∇|² ≈ (2πf)²), each at several weights w·(D/r0 / 2)^(5/3); after
   the sharpest fusion at D/r0 × 0.3 (``SHARPEST_DR0_SCALE``).
2. **Band fit**: the clean image's spectrum regressed, per radial frequency band (32 bands to 0.5 cycles/px), on the
   spectra of (a) the deconvolved mean alone (one gain per band: a re-tuned filter) and (b) the deconvolved mean and
   the sharpest fusion together (two real weights per band). Fit on half the clips of a bin and scored on the other
   half, then the halves swapped (two-fold cross-validation). If (b) does not beat (a), no linear filter finds in the
   sharpest fusion anything the deconvolved mean lacks.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
from bench_fusion_peer import MARGIN, global_offset, move, psnr_offset_removed  # noqa: E402

from d2turb.clip import SHARPEST_DR0_SCALE, ClipRestorer, PhysicsDeblur  # noqa: E402
from d2turb.data.sequence import SequenceDataset  # noqa: E402
from d2turb.eval.clips import physics_deblur_for  # noqa: E402

BANDS = 32
# (prior, weight at D/r0 = 2): the Laplacian at the weight chosen with it, the gradient at 1/4, 1/8, 1/16 of that
PRIORS = [("laplacian", 0.002), ("gradient", 0.0005), ("gradient", 0.00025), ("gradient", 0.000125)]


def chw(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a)).permute(2, 0, 1)


def hwc(t: torch.Tensor) -> np.ndarray:
    return t.clamp(0, 1).permute(1, 2, 0).numpy()


def plain_psnr(x: np.ndarray, gt: np.ndarray) -> float:
    c = (slice(MARGIN, -MARGIN), slice(MARGIN, -MARGIN))
    return float(10 * np.log10(1 / max(float(np.mean((x[c] - gt[c]) ** 2)), 1e-10)))


def deblur(base: PhysicsDeblur, prior: str, weight: float, dr0_scale: float = 1.0) -> PhysicsDeblur:
    balance = weight * (base.dr0 / 2) ** (5 / 3)
    return PhysicsDeblur(base.dr0 * dr0_scale, base.lambda_over_d_px, balance, base.modulation, prior=prior)


def radius(h: int, w: int) -> np.ndarray:
    """|f| (cycles/px) on the fft2 grid of an (h, w) image."""
    return np.sqrt(np.fft.fftfreq(h)[:, None] ** 2 + np.fft.fftfreq(w)[None] ** 2)


def band_index(h: int, w: int) -> np.ndarray:
    return np.minimum((radius(h, w) / 0.5 * BANDS).astype(int), BANDS - 1)


def aligned_spectra(images: dict, gt: np.ndarray, ref: str) -> dict:
    """Spectra of the images moved by the global offset of ``ref`` onto ``gt`` (border cropped), and of ``gt``."""
    shift = global_offset(images[ref], gt)
    h, w = gt.shape[:2]
    c = (slice(MARGIN, h - MARGIN), slice(MARGIN, w - MARGIN))
    out = {"gt": np.fft.fft2(gt[c], axes=(0, 1)).astype(np.complex64)}
    for k, v in images.items():
        out[k] = np.fft.fft2(move(v, shift)[c], axes=(0, 1)).astype(np.complex64)
    return out


def fit_bands(frames: list[dict], inputs: tuple[str, ...]) -> np.ndarray:
    """Least-squares real weights per band: gt ≈ Σ_i a_i(band)·input_i."""
    band = band_index(*frames[0]["spec"]["gt"].shape[:2])
    coef = np.zeros((BANDS, len(inputs)))
    for k in range(BANDS):
        sel = band == k
        x = np.stack([np.concatenate([f["spec"][n][sel].ravel() for f in frames]) for n in inputs], 1)
        g = np.concatenate([f["spec"]["gt"][sel].ravel() for f in frames])
        normal = np.real(x.conj().T @ x)
        coef[k] = np.linalg.solve(normal + 1e-9 * np.trace(normal) * np.eye(len(inputs)), np.real(x.conj().T @ g))
    return coef


def apply_bands(images: list[np.ndarray], coef: np.ndarray) -> np.ndarray:
    r = radius(*images[0].shape[:2])
    centres = (np.arange(BANDS) + 0.5) / BANDS * 0.5
    gains = [np.interp(r, centres, coef[:, i])[..., None] for i in range(len(images))]
    total = sum(g * np.fft.fft2(im, axes=(0, 1)) for g, im in zip(gains, images))
    return np.real(np.fft.ifft2(total, axes=(0, 1))).astype(np.float32)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clips", required=True, help="a sequence dataset (make-dataset --frames N)")
    ap.add_argument("--temporal", type=int, default=32)
    ap.add_argument("--stride", type=int, default=4)
    ap.add_argument("--max-clips", type=int, default=None)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    torch.set_num_threads(1)
    data = SequenceDataset(a.clips)
    n = len(data) if a.max_clips is None else min(len(data), a.max_clips)
    scores: dict[str, dict[str, list]] = {}
    frames = []
    for i in range(n):
        item, record = data[i], data.records[i]
        gt = item["gt"].permute(1, 2, 0).numpy()
        base = physics_deblur_for(record, item["depth"])
        fused = {}
        for fusion in ("mean", "sharpest"):
            restorer = ClipRestorer(temporal=a.temporal, passes=2, fusion=fusion)
            fused[fusion] = [hwc(o.fused) for o in restorer.restore(item["turb"]) if o.index % a.stride == 0]
        rows = scores.setdefault(record["bin"], {})
        for mean, sharp in zip(fused["mean"], fused["sharpest"]):
            out = {"mean": mean, "sharpest": sharp}
            for prior, weight in PRIORS:
                out[f"mean + {prior} {weight:g}"] = hwc(deblur(base, prior, weight)(chw(mean)))
                out[f"sharpest + {prior} {weight:g}"] = hwc(deblur(base, prior, weight, SHARPEST_DR0_SCALE)(chw(sharp)))
            for name, img in out.items():
                rows.setdefault(name, []).append(psnr_offset_removed(img, gt))
                rows.setdefault(name + " (plain)", []).append(plain_psnr(img, gt))
            used = {"W": out["mean + gradient 0.00025"], "S": sharp}
            spec = aligned_spectra(used, gt, "W")
            frames.append({"id": item["id"], "bin": record["bin"], "spec": spec, "gt": gt, **used})
        print(i, record["bin"], time.strftime("%H:%M:%S"), flush=True)
    res = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "settings": vars(a),
        "score": "PSNR (dB) with the global sub-pixel offset removed (and plain), 8 px border cropped",
        "prior_scan": {b: {k: float(np.mean(v)) for k, v in rows.items()} for b, rows in scores.items()},
        "band_fit": {},
    }
    ids = sorted({f["id"] for f in frames})
    half = set(ids[::2])
    for b in scores:
        fit = {"deconvolved mean (gradient 0.00025)": [], "re-tuned per band": [], "+ sharpest fusion per band": []}
        for train in (half, set(ids) - half):
            tr = [f for f in frames if f["bin"] == b and f["id"] in train]
            te = [f for f in frames if f["bin"] == b and f["id"] not in train]
            if not tr or not te:
                continue
            one, two = fit_bands(tr, ("W",)), fit_bands(tr, ("W", "S"))
            for f in te:
                outs = (f["W"], apply_bands([f["W"]], one), apply_bands([f["W"], f["S"]], two))
                for key, img in zip(fit, outs):
                    fit[key].append(psnr_offset_removed(img, f["gt"]))
        res["band_fit"][b] = {k: float(np.mean(v)) for k, v in fit.items()}
    text = json.dumps(res, indent=1)
    print(text)
    if a.json:
        Path(a.json).write_text(text + "\n")


if __name__ == "__main__":
    main()
