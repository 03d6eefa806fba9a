# validation of d2turb.clip.strength on simulated clips, with and without a ±3 px camera shake (docs/measure.md):
#   python3 validate.py OUT.jsonl "PATTERN" ["PATTERN" ...]   (default: val.jsonl "clips/val*")
#   python3 validate.py --stats-only "PATTERN" ...   registers the clips into stats/ only (no estimate, no output):
#   the slow part can run while the calibration is chosen, without looking at the validation clips' results
# appends one JSON line per clip (skipping clips already in OUT.jsonl): truth, optics, scene folder, depth mode and
# the plain and shaken results (or the refusal). The registered structure sums are kept in stats/: a new OUT.jsonl
# after a change of the estimator (not of the registration) refits them in seconds.
import glob
import json
import os
import sys
import time
import zlib

import cv2
import numpy as np

from d2turb.clip import motion
from d2turb.clip import strength as M
from d2turb.errors import D2TurbError
from d2turb.io import list_images, read_image

STATS_ONLY = "--stats-only" in sys.argv
args = [a for a in sys.argv[1:] if a != "--stats-only"]
out_path = None if STATS_ONLY else (args[0] if args else "val.jsonl")
patterns = (args if STATS_ONLY else args[1:]) or ["clips/val*"]
done = set()
if out_path and os.path.exists(out_path):
    done = {json.loads(line)["clip"] for line in open(out_path)}
os.makedirs("stats", exist_ok=True)


def measure(frames, optics, cache):
    """measure_clip(frames, optics) without windows, in its steps, keeping the registered structure sums in
    ``cache`` (stats/CLIP_plain.npz, _shake.npz; a refusal as its message): a second run with the same cache refits
    them with the current estimator (gain table, interval) instead of registering the clip again."""
    t0 = time.time()
    optics = M.as_optics(optics)
    try:
        if os.path.exists(cache):
            z = np.load(cache)
            if "error" in z:
                raise D2TurbError(str(z["error"]))
            num, pairs, series, diag = (
                z["num"],
                z["pairs"],
                [tuple(s) for s in z["series"].tolist()],
                json.loads(str(z["diag"])),
            )
        else:
            gray, _ = motion.centre_crop(motion.gray_frames(frames), 320)
            try:
                flows, mask, diag = M.register_measurable(gray)
            except D2TurbError as exc:
                np.savez(cache, error=str(exc))
                raise
            num, pairs, series = M.lag_sums(flows, mask, M.separations_for(*mask.shape))
            np.savez(cache, num=num, pairs=pairs, series=np.array(series), diag=json.dumps(diag))
        if STATS_ONLY:
            return {}
        r = M.estimate_from_sums(num, pairs, series, optics, bootstrap=200).to_dict()
    except D2TurbError as exc:  # a refusal is a result too
        return {"error": str(exc)}
    return {k: r[k] for k in ("dr0", "dr0_ci", "dr0_log_sd")} | {
        "valid_fraction": diag["valid_fraction"],
        "fit": r["fit"],
        "s": time.time() - t0,
    }


clips = sorted({c for p in patterns for c in glob.glob(p)}, key=lambda c: (c.rsplit("_", 1)[-1].zfill(4), c))
for d in clips:  # round-robin over D/r0
    if (
        not os.path.exists(f"{d}/meta.json")
        or os.path.exists(f"{d}.lock")
        or d in done
        or d.endswith((".err", ".lock"))
    ):
        continue
    base = os.path.basename(d)
    if STATS_ONLY and all(os.path.exists(f"stats/{base}_{n}.npz") for n in ("plain", "shake")):
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
    rng = np.random.default_rng(zlib.crc32(d.encode()))  # the same shake in every run
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
    rec = {
        "clip": d,
        "dr0_true": meta["dr0"],  # with --depth prior: the D/r0 of the farthest point (the modulation is 1 there)
        "wind": meta["wind_m_s"],
        "image": meta["input"],
        "scene": "sunhays_outdoor"
        if "_SRF_8_" in meta["input"]
        else "bsd100"
        if "_SRF_2_" in meta["input"]
        else "other",
        "geometry": "field" if os.path.basename(d).startswith(("valf_", "valnf_")) else "default",
        "depth": meta["depth"],
        "footprint_px": meta["aperture_m"] / (meta["ifov_rad"] * meta["path_length_m"]),
    }
    for name, fr in (("plain", frames), ("shake", shaken)):
        rec[name] = measure(fr, optics, f"stats/{os.path.basename(d)}_{name}.npz")
    if STATS_ONLY:
        continue
    with open(out_path, "a") as fh:
        fh.write(json.dumps(rec) + "\n")
    print(json.dumps(rec), flush=True)
