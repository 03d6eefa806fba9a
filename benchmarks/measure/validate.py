# validation of d2turb.measure on simulated clips (clips/val_*), with and without a ±3 px camera shake
import glob
import json
import os
import sys
import time

import cv2
import numpy as np

from d2turb import measure as M
from d2turb.io import list_images, read_image

out_path = sys.argv[1] if len(sys.argv) > 1 else "val.jsonl"
pattern = sys.argv[2] if len(sys.argv) > 2 else "clips/val_*"
done = set()
if os.path.exists(out_path):
    done = {json.loads(line)["clip"] for line in open(out_path)}
for d in sorted(glob.glob(pattern), key=lambda c: (c.rsplit("_", 1)[-1].zfill(4), c)):  # round-robin over D/r0
    if not os.path.exists(f"{d}/meta.json") or d in done or d.endswith(".err"):
        continue
    meta = json.load(open(f"{d}/meta.json"))
    optics = dict(
        aperture_m=meta["aperture_m"],
        wavelength_m=meta["reference_wavelength_m"],
        ifov_rad=meta["ifov_rad"],
        path_length_m=meta["path_length_m"],
        fps=meta["fps"],
    )
    frames = [read_image(f).permute(1, 2, 0).numpy() for f in list_images(f"{d}/turb")]
    rng = np.random.default_rng(abs(hash(d)) % 2**32)
    shaken = []
    for f in frames:  # a random global translation of up to ±3 px per frame
        dx, dy = rng.uniform(-3, 3, 2)
        shaken.append(
            cv2.warpAffine(
                f,
                np.float32([[1, 0, dx], [0, 1, dy]]),
                f.shape[1::-1],
                flags=cv2.INTER_CUBIC,
                borderMode=cv2.BORDER_REFLECT,
            )
        )
    rec = {"clip": d, "dr0_true": meta["dr0"], "wind": meta["wind_m_s"], "image": meta["input"]}
    for name, fr in (("plain", frames), ("shake", shaken)):
        t0 = time.time()
        try:
            r = M.measure_clip(fr, optics, bootstrap=200)
            rec[name] = {k: r[k] for k in ("dr0", "dr0_ci", "valid_fraction")} | {
                "fit": r["fit"],
                "s": time.time() - t0,
            }
        except Exception as exc:  # a refusal is a result too
            rec[name] = {"error": str(exc)}
    with open(out_path, "a") as fh:
        fh.write(json.dumps(rec) + "\n")
    print(json.dumps(rec), flush=True)
