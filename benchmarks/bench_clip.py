"""Clip restoration throughput per stage and peak memory over clip length (issue 23).

    python3 benchmarks/bench_clip.py [--sizes 256x256 1280x720 1920x1080] [--frames 24] [--temporal 24]
                                     [--preset fast] [--passes 2] [--fusion mean] [--rss 100 1000]
                                     [--rss-size 64x64] [--json FILE]

1. ``ClipRestorer`` on a synthetic clip (a natural image under smooth random warps, so DIS has real work) at each
   size: frames/s of the whole stream with ``--deblur none`` and with the physics Wiener filter, and the time per
   frame of each stage (registration = DIS + phase correlation, unwarp + fusion, deblur), after a warm-up window.
2. Peak RSS of a fresh process restoring a streamed clip of each ``--rss`` length (frames generated on the fly, not
   held): memory must not grow with the clip's length.
Prints one JSON object (and writes it to --json FILE); the load average is recorded (the machine is shared).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time

import numpy as np
from scipy import ndimage
from skimage import data as skdata

CHILD = """
import sys, numpy as np
from d2turb.clip import ClipRestorer
h, w, n, t = map(int, sys.argv[1:5])
fusion = sys.argv[5]
rng = np.random.default_rng(0)
base = rng.random((h, w, 3), dtype=np.float32)
frames = (np.clip(base + 0.02 * rng.standard_normal((h, w, 3), dtype=np.float32), 0, 1) for _ in range(n))
count = sum(1 for _ in ClipRestorer(temporal=t, fusion=fusion).restore(frames))
hwm = next(ln for ln in open("/proc/self/status") if ln.startswith("VmHWM:")).split()[1]
print("RESULT", count, hwm)  # VmHWM: this process's own peak (ru_maxrss would carry the parent's over exec)
"""


def synthetic_clip(h: int, w: int, frames: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    img = skdata.astronaut().astype(np.float32) / 255.0
    img = np.stack([ndimage.zoom(img[..., c], (h / img.shape[0], w / img.shape[1]), order=1) for c in range(3)], -1)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    out = []
    for _ in range(frames):
        small = rng.standard_normal((2, max(2, h // 16), max(2, w // 16)))
        field = np.stack([ndimage.zoom(small[c], (h / small.shape[1], w / small.shape[2]), order=3) for c in (0, 1)])
        field *= 1.5 / max(field.std(), 1e-6)
        import cv2

        out.append(
            cv2.remap(
                img,
                xx + field[0].astype(np.float32),
                yy + field[1].astype(np.float32),
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            )
        )
    return out


def stage_times(h: int, w: int, frames: int, temporal: int, preset: str, passes: int, fusion: str = "mean") -> dict:
    import d2turb.clip.pipeline as clip
    from d2turb.clip import ClipRestorer, PhysicsDeblur

    data = synthetic_clip(h, w, frames)
    result = {}
    for name, deblur in (("none", "none"), ("physics", PhysicsDeblur(3.0, 2.0))):
        timers = {"registration": 0.0, "unwarp_fusion": 0.0, "deblur": 0.0}
        r = ClipRestorer(temporal=temporal, preset=preset, passes=passes, deblur=deblur, fusion=fusion)
        originals = (clip.DenseFlow.__call__, clip.global_shift_px, clip.remap, ClipRestorer._reference)
        sharp = (clip.sharp_coefficients, clip.SharpestFusion.fuse)

        def timed(key, fn, timers=timers):
            def wrapper(*args, **kwargs):
                t = time.perf_counter()
                try:
                    return fn(*args, **kwargs)
                finally:
                    timers[key] += time.perf_counter() - t

            return wrapper

        clip.DenseFlow.__call__ = timed("registration", originals[0])
        clip.global_shift_px = timed("registration", originals[1])
        clip.remap = timed("unwarp_fusion", originals[2])
        ClipRestorer._reference = timed("unwarp_fusion", originals[3])
        clip.sharp_coefficients = timed("unwarp_fusion", sharp[0])
        clip.SharpestFusion.fuse = timed("unwarp_fusion", sharp[1])
        if r.deblur is not None:
            r.deblur = timed("deblur", r.deblur)
        try:
            t0 = time.perf_counter()
            n = sum(1 for _ in r.restore(data))
            wall = time.perf_counter() - t0
        finally:
            clip.DenseFlow.__call__, clip.global_shift_px, clip.remap, ClipRestorer._reference = originals
            clip.sharp_coefficients, clip.SharpestFusion.fuse = sharp
        result[name] = {
            "frames": n,
            "frames_per_s": n / wall,
            "s_per_frame": {k: v / n for k, v in timers.items()},
        }
    return result


def peak_rss(h: int, w: int, frames: int, temporal: int, fusion: str = "mean") -> dict:
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(h), str(w), str(frames), str(temporal), fusion],
        capture_output=True,
        text=True,
    )
    line = next(ln for ln in out.stdout.splitlines() if ln.startswith("RESULT"))
    _, count, kib = line.split()
    return {"frames": int(count), "peak_rss_mib": int(kib) / 1024}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", nargs="+", default=["256x256", "1280x720", "1920x1080"])
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--temporal", type=int, default=24)
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--passes", type=int, default=2)
    ap.add_argument("--fusion", default="mean")
    ap.add_argument("--rss", nargs="*", type=int, default=[100, 1000])
    ap.add_argument("--rss-size", default="64x64")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    res = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "load_average": os.getloadavg(),
        "date": time.strftime("%Y-%m-%d"),
        "settings": vars(a),
        "speed": {},
        "memory": {},
    }
    for size in a.sizes:
        w, h = map(int, size.split("x"))
        res["speed"][size] = stage_times(h, w, a.frames, a.temporal, a.preset, a.passes, a.fusion)
    rw, rh = map(int, a.rss_size.split("x"))
    for n in a.rss:
        res["memory"][str(n)] = peak_rss(rh, rw, n, a.temporal, a.fusion)
    text = json.dumps(res, indent=1)
    print(text)
    if a.json:
        with open(a.json, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
