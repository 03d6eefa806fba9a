# 256² centre crops of the clean images: cal/ (first 100 bsds500 images: a train folder, calibration only), calo/
# (outdoor photographs of the train folders camvid, strecha_mvs, sfm_landmarks, spread over each folder: calibration
# only) and img/ (first 70 bsd100 and all 69 sunhays_outdoor images: the test folders of the fixed split, validation
# only); img2/ (the other 30 bsd100 images: validation only, the fourth batch of gen.py); calt/ (fourth calibration:
# the 32 least textured 256² centre crops of the train folders, by the textured fraction of the crop's inner area,
# structure tensor as d2turb.clip.strength; bsds500 only beyond the first 100, none of calo/); cal5/ (fifth
# calibration: the next 64 bsds500 crops, none of calt/)
import glob
import os
import sys

import numpy as np
from PIL import Image

from d2turb.clip import motion

C = sys.argv[1] if len(sys.argv) > 1 else "/work/shared/data/clean"
outdoor = [sorted(glob.glob(f"{C}/camvid/*"))[::22][:12], sorted(glob.glob(f"{C}/strecha_mvs/*"))[::3][:10],
           sorted(glob.glob(f"{C}/sfm_landmarks/*"))[::2][:10]]  # fmt: skip
outdoor = [f for k in range(12) for folder in outdoor for f in folder[k : k + 1]]  # round robin over the folders


def centre_crop(f):
    im = Image.open(f).convert("RGB")
    w, h = im.size
    s = min(w, h, 256)
    return im.crop(((w - s) // 2, (h - s) // 2, (w - s) // 2 + s, (h - s) // 2 + s)), s


def least_textured(n):
    used = {os.path.basename(f).split("_", 1)[1] for f in glob.glob("calo/*.png")}
    scored = []
    for folder in ("camvid", "sfm_landmarks", "strecha_mvs", "bsds500", "urban100", "t91"):
        files = sorted(glob.glob(f"{C}/{folder}/*"))[100 if folder == "bsds500" else 0 :]
        for f in files:
            im, s = centre_crop(f)
            if s < 256 or os.path.basename(f).rsplit(".", 1)[0] + ".png" in used:
                continue
            lam = motion.structure_min_eigenvalue(np.asarray(im.convert("L"), np.float32))[
                motion.MARGIN_PX : -motion.MARGIN_PX
            ]
            scored.append((float((lam[:, motion.MARGIN_PX : -motion.MARGIN_PX] > motion.TEXTURE_MIN).mean()), f))
    return [f for _, f in sorted(scored)[:n]]


for folder, files in (
    ("cal", sorted(glob.glob(f"{C}/bsds500/*"))[:100]),
    ("calo", outdoor),
    ("img", sorted(glob.glob(f"{C}/bsd100/*.png"))[:70] + sorted(glob.glob(f"{C}/sunhays_outdoor/*"))[:70]),
    ("img2", sorted(glob.glob(f"{C}/bsd100/*.png"))[70:]),
    ("calt", None),
    ("cal5", None),
):
    if folder == "calt":
        files = least_textured(32)
    elif folder == "cal5":  # the fifth calibration: 64 bsds500 crops beyond the first 100, none of calt/
        taken = {os.path.basename(f).split("_", 1)[1] for f in glob.glob("calt/*.png")}
        files = [f for f in sorted(glob.glob(f"{C}/bsds500/*"))[100:] if os.path.basename(f).rsplit(".", 1)[0] + ".png"
                 not in taken][:64]  # fmt: skip
    os.makedirs(folder, exist_ok=True)
    for i, f in enumerate(files):
        stem = os.path.basename(f).rsplit(".", 1)[0]
        numbered = folder in ("calo", "calt", "cal5")  # in that order (calt/: least textured first)
        out = f"{folder}/{i:02d}_{stem}.png" if numbered else f"{folder}/{stem}.png"
        if os.path.exists(out):
            continue
        centre_crop(f)[0].save(out)
