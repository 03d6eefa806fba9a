"""Fusion of registered clip frames against the truth: the mean, d2turb's other fusions and, optionally, the DT-CWT
fusion of Anantrasirichai et al. (IEEE TIP 2013) on the same registered windows (issue 40).

    PYTHONPATH=src python3 benchmarks/bench_fusion_peer.py --clips val_clips [--fusions mean sharpest]
        [--deblur 1 0.5@0.7] [--temporal 32] [--stride 4] [--peer-python PY --peer-src DIR] [--json FILE]

For each clip of a sequence dataset (``make-dataset --frames N``, docs/clips.md) and each fusion, ``ClipRestorer``
(DIS fast, 2 passes, window ``--temporal``) restores the clip with ``--deblur none``; every ``--stride``-th output is
scored as fused and after the physics Wiener filter at the clip's true D/r0 and optics with its Laplacian weight × M
and D/r0 × S for each ``--deblur M@S``. Scores are PSNR with the global offset removed: the output is moved onto
the clean image by the sub-pixel shift that phase correlation finds between them
(``skimage.registration.phase_cross_correlation``, 1/20 px; bicubic), and both are cropped by 8 px: a clip cannot
see its own mean tilt, which plain PSNR punishes.

The peer (optional): the windows of every ``--peer-stride``-th output of the mean run (the same registered frames)
are fused by ``--peer-python`` (a scratch environment with PyPI's ``dtcwt``; numpy < 2) with the fusion steps of
rjw57/dtcwtfusion (``--peer-src``: a checkout of it; its ``transform_frames`` / ``reconstruct`` / ``shrink_coeffs``,
and the fusion of its ``main``: mean low-pass, mean phase, the largest magnitude of the inliers, < 2 × the median),
per colour channel, 7 levels; with and without its final bivariate shrinkage. Neither is a dependency of d2turb.
Prints one JSON object (and writes it to --json FILE).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from skimage.registration import phase_cross_correlation

from d2turb.clip import ClipRestorer, PhysicsDeblur
from d2turb.clip.sharpest import sharpest_fusion
from d2turb.data.sequence import SequenceDataset
from d2turb.eval.clips import physics_deblur_for

MARGIN = 8  # px cropped on every side before scoring

PEER_CHILD = r"""
import sys, numpy as np
sys.path.insert(0, sys.argv[1])
from dtcwtfusion.fuseimages import transform_frames, reconstruct, shrink_coeffs  # rjw57/dtcwtfusion

def fuse(frames, shrink, nlevels=7):  # the fusion of dtcwtfusion's main(): max-inlier magnitude, mean phase
    lowpasses, highpasses = transform_frames(frames, nlevels)
    lowpass_mean = np.mean(lowpasses, axis=2)
    phases, mags_out = [], []
    for sb in highpasses:
        s = np.sum(sb, axis=3); m = np.abs(s); s /= np.where(m != 0, m, 1); phases.append(s)
        mags = np.abs(sb); thresh = 2 * np.median(mags, axis=3)[..., None]
        mags_out.append(np.max(np.where(mags < thresh, mags, 0), axis=3))
    hp = tuple(a * p for a, p in zip(mags_out, phases))
    return reconstruct(lowpass_mean, shrink_coeffs(hp) if shrink else hp)

for path in sys.argv[2:]:
    st = np.load(path)["stack"].astype(np.float64)  # (N, H, W, C)
    for shrink in (False, True):
        out = np.stack([fuse(np.moveaxis(st[..., c], 0, -1), shrink) for c in range(st.shape[-1])], -1)
        out = out[: st.shape[1], : st.shape[2]].astype(np.float32)
        np.save(path[:-4] + ("_shrink" if shrink else "_max") + ".npy", out)
"""


def global_offset(image: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """The global sub-pixel shift (dy, dx) that moves ``image`` (H,W,C) onto ``truth``: phase correlation of the grey
    images, 1/20 px."""
    shift, _, _ = phase_cross_correlation(truth.mean(2), image.mean(2), upsample_factor=20, normalization=None)
    return shift


def move(image: np.ndarray, shift) -> np.ndarray:
    """``image`` (H,W,C) shifted by (dy, dx) px, bicubic, borders mirrored."""
    h, w = image.shape[:2]
    m = np.float32([[1, 0, shift[1]], [0, 1, shift[0]]])
    return cv2.warpAffine(image, m, (w, h), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)


def psnr_offset_removed(image: np.ndarray, truth: np.ndarray, margin: int = MARGIN) -> float:
    """PSNR (dB, range 1) of ``image`` (H,W,C) against ``truth`` after the global sub-pixel shift between them is
    removed (:func:`global_offset`, :func:`move`), both cropped by ``margin`` px."""
    image, truth = np.asarray(image, np.float32), np.asarray(truth, np.float32)
    moved = move(image, global_offset(image, truth))
    h, w = image.shape[:2]
    crop = (slice(margin, h - margin), slice(margin, w - margin))
    mse = float(np.mean((np.clip(moved, 0, 1)[crop] - truth[crop]) ** 2))
    return 10 * np.log10(1 / max(mse, 1e-10))


def hwc(t) -> np.ndarray:
    return t.clamp(0, 1).permute(1, 2, 0).numpy()


def score_clip(item, record, fusion, a, peer_dir=None) -> dict:
    gt = item["gt"].permute(1, 2, 0).numpy()
    base = physics_deblur_for(record, item["depth"])
    deblurs = {}
    for v in a.deblur:  # "M" or "M@S": Laplacian weight x M, the OTF at D/r0 x S
        m, _, s = v.partition("@")
        deblurs[v] = PhysicsDeblur(
            base.dr0 * float(s or 1), base.lambda_over_d_px, balance=base.balance * float(m), modulation=base.modulation
        )
    restorer = ClipRestorer(temporal=a.temporal, passes=2, fusion=fusion)
    if peer_dir is not None:  # keep the registered windows of the peer's frames (the same frames every fusion sees)
        original = restorer._output

        def output(buf, index, length):
            if index % a.peer_stride == 0:
                stack = np.stack([buf[j].warped[-1] for j in restorer._window(buf, index, length)])
                np.savez(peer_dir / f"{item['id']}_{index:04d}.npz", stack=stack.astype(np.float32))
            return original(buf, index, length)

        restorer._output = output
    scores: dict[str, list] = {"input": [], "fused": []} | {f"restored {v}": [] for v in a.deblur}
    t0 = time.perf_counter()
    fuse_s = 0.0
    for o in restorer.restore(item["turb"]):
        if o.index % a.stride:
            continue
        t1 = time.perf_counter()
        scores["input"].append(psnr_offset_removed(hwc(item["turb"][o.index]), gt))
        scores["fused"].append(psnr_offset_removed(hwc(o.fused), gt))
        for m, fn in deblurs.items():
            scores[f"restored {m}"].append(psnr_offset_removed(hwc(fn(o.fused)), gt))
        fuse_s -= time.perf_counter() - t1  # scoring time is not the method's
    wall = time.perf_counter() - t0 + fuse_s
    return {k: float(np.mean(v)) for k, v in scores.items()} | {"s_per_clip": wall}


def run_peer(a, peer_dir: Path, data, run_child: bool = True) -> dict:
    """Score the peer's fusions of the saved windows beside the mean and d2turb's sharpest fusion of the same frames
    (at once: :func:`~d2turb.clip.fusion.sharpest_fusion`, the window's median as every frame's reference)."""
    files = sorted(str(p) for p in peer_dir.glob("*.npz"))
    child = peer_dir / "peer_child.py"
    child.write_text(PEER_CHILD)
    t0 = time.perf_counter()
    if run_child:
        subprocess.run([a.peer_python, str(child), a.peer_src, *files], check=True)
    wall = time.perf_counter() - t0
    gts = {data[i]["id"]: (data[i]["gt"].permute(1, 2, 0).numpy(), data.records[i]["bin"]) for i in range(a.n)}
    rows: dict[str, dict] = {}
    for f in files:
        name = Path(f).stem
        clip_id = name.rsplit("_", 1)[0]
        gt, bin_ = gts[clip_id]
        stack = np.load(f)["stack"]
        own = {"mean (same frames)": stack.mean(0), "sharpest (same frames)": sharpest_fusion(list(stack))}
        for key, suffix in [(k, None) for k in own] + [("dtcwt max-inlier", "_max"), ("dtcwt + shrinkage", "_shrink")]:
            img = own[key] if suffix is None else np.load(f[:-4] + suffix + ".npy")
            rows.setdefault(key, {}).setdefault(bin_, []).append(psnr_offset_removed(img, gt))
    out = {k: {b: float(np.mean(v)) for b, v in per.items()} for k, per in rows.items()}
    return {"bins": out, "windows": len(files), "s_per_window": wall / max(len(files), 1)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--clips", required=True, help="a sequence dataset (make-dataset --frames N)")
    ap.add_argument("--fusions", nargs="+", default=["mean", "sharpest"])
    ap.add_argument(
        "--deblur", nargs="+", default=["1"], help="physics deblurs: M or M@S (Laplacian weight x M, OTF at D/r0 x S)"
    )
    ap.add_argument("--temporal", type=int, default=32)
    ap.add_argument("--stride", type=int, default=4)
    ap.add_argument("--max-clips", type=int, default=None)
    ap.add_argument("--skip", type=int, default=0, help="start at this clip")
    ap.add_argument("--peer-python", default=None, help="python of a scratch venv with dtcwt (numpy < 2)")
    ap.add_argument("--peer-src", default=None, help="a checkout of rjw57/dtcwtfusion")
    ap.add_argument("--peer-stride", type=int, default=16)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    data = SequenceDataset(a.clips)
    a.n = len(data) if a.max_clips is None else min(len(data), a.max_clips)
    res = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "load_average": os.getloadavg(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "settings": {k: v for k, v in vars(a).items() if k != "n"},
        "score": "PSNR (dB) with the global sub-pixel offset removed, 8 px border cropped",
        "clips": [],
    }
    with tempfile.TemporaryDirectory() as tmp:
        peer_dir = Path(tmp) if a.peer_python else None
        for i in range(a.skip, a.n):
            item, record = data[i], data.records[i]
            row = {"id": item["id"], "bin": record["bin"], "dr0": float(record["dr0"])}
            for k, fusion in enumerate(a.fusions):
                row[fusion] = score_clip(item, record, fusion, a, peer_dir if k == 0 else None)
            res["clips"].append(row)
            print(json.dumps(row), flush=True)
        if peer_dir is not None:
            res["peer"] = run_peer(a, peer_dir, data)
    bins: dict[str, dict] = {}
    for row in res["clips"]:
        for fusion in a.fusions:
            for key, v in row[fusion].items():
                bins.setdefault(row["bin"], {}).setdefault(fusion, {}).setdefault(key, []).append(v)
    res["bins"] = {
        b: {f: {k: float(np.mean(v)) for k, v in d.items()} | {"clips": len(d["fused"])} for f, d in per.items()}
        for b, per in bins.items()
    }
    text = json.dumps(res, indent=1)
    print(text)
    if a.json:
        Path(a.json).write_text(text + "\n")


if __name__ == "__main__":
    main()
