"""Hashes of every clip output in 41 modes (4 fusions x 4 deblurs, 8-bit and float frames, camera followed or not,
fallback and tone guard off, 1-3 rounds, a tensor clip shorter than its window): a refactor of the clip room must
leave them equal. Usage: ``python benchmarks/clip_identity.py before.json``, change the code, ``... after.json``,
``cmp before.json after.json`` (single-threaded; compare on one machine: BLAS and OpenCV take CPU-specific paths)."""

import hashlib
import json
import sys

import cv2
import numpy as np
import torch

from d2turb.clip import ClipRestorer, PhysicsDeblur
from d2turb.clip.blind import BlindDeblur


def clip(seed, n=20, h=72, w=88, shake=True, moving=True, u8=True):
    """A smooth scene, shaken (a 6-px jump mid-clip), a bright patch crossing it, a little noise."""
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.random((h + 40, w + 40, 3)).astype(np.float32), (0, 0), 2)
    base = (base - base.min()) / (base.max() - base.min())
    frames = []
    for t in range(n):
        dx, dy = rng.normal(0, 1.5, 2) if shake else (0, 0)
        dx += 6 if shake and t == n // 2 else 0
        m = np.float32([[1, 0, 20 + dx], [0, 1, 20 + dy]])
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        f = cv2.warpAffine(base, m, (w, h), flags=flags, borderMode=cv2.BORDER_REFLECT)
        f = f + rng.normal(0, 0.01, f.shape).astype(np.float32)
        if moving:
            f[20:36, 4 + 3 * t : 18 + 3 * t] = 0.9
        f = np.clip(f, 0, 1).astype(np.float32)
        frames.append(np.rint(f * 255).astype(np.uint8) if u8 else f)
    return frames


def digest(a) -> str:
    a = a.detach().numpy() if isinstance(a, torch.Tensor) else a
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()[:16]


def run(name, frames, **kw) -> dict:
    outs = ClipRestorer(**kw).restore(frames)
    rows = [[digest(f.restored), digest(f.fused), digest(f.bwd_flow_hwc_px), digest(f.fallback), str(f.camera_px)]
            for f in outs]  # fmt: skip
    return {name: rows}


class Model:
    """A model-like deblur: (3,H,W) → (3,H,W)."""

    def __call__(self, x):
        return (x * 0.9 + 0.05).clamp(0, 1)


def main(out: str) -> None:
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    res = {}
    for u8 in (True, False):
        fr = clip(1, u8=u8)
        for fusion in ("mean", "robust", "fba", "sharpest"):
            deblurs = {"none": "none", "physics": PhysicsDeblur.for_fusion(2.0, 2.0, fusion)}
            deblurs |= {"blind": BlindDeblur(fusion=fusion), "model": Model()}
            for name, deblur in deblurs.items():
                res |= run(f"{u8}-{fusion}-{name}", fr, temporal=8, fusion=fusion, deblur=deblur)
        res |= run(f"{u8}-nostab", fr, temporal=6, stabilise=False)
        res |= run(f"{u8}-nofallback", fr, temporal=6, fallback=False, tone_guard=False, deblur=Model())
        res |= run(f"{u8}-passes1", fr, temporal=5, passes=1)
        res |= run(f"{u8}-passes3-medium", fr, temporal=7, passes=3, preset="medium")
    fr = [torch.from_numpy(f.transpose(2, 0, 1).astype(np.float32) / 255) for f in clip(2, n=9, shake=False)]
    res |= run("tensor-short", fr, temporal=16)
    with open(out, "w") as fh:
        json.dump(res, fh, indent=0)
    print(len(res), "modes")


if __name__ == "__main__":
    main(sys.argv[1])
