# 256² centre crops of the clean images: cal/ (first 100 bsds500 images: a train folder, calibration only), calo/
# (outdoor photographs of the train folders camvid, strecha_mvs, sfm_landmarks, spread over each folder: calibration
# only) and img/ (first 70 bsd100 and all 69 sunhays_outdoor images: the test folders of the fixed split, validation
# only)
import glob
import os
import sys

from PIL import Image

C = sys.argv[1] if len(sys.argv) > 1 else "/work/shared/data/clean"
outdoor = [sorted(glob.glob(f"{C}/camvid/*"))[::22][:12], sorted(glob.glob(f"{C}/strecha_mvs/*"))[::3][:10],
           sorted(glob.glob(f"{C}/sfm_landmarks/*"))[::2][:10]]  # fmt: skip
outdoor = [f for k in range(12) for folder in outdoor for f in folder[k : k + 1]]  # round robin over the folders
for folder, files in (
    ("cal", sorted(glob.glob(f"{C}/bsds500/*"))[:100]),
    ("calo", outdoor),
    ("img", sorted(glob.glob(f"{C}/bsd100/*.png"))[:70] + sorted(glob.glob(f"{C}/sunhays_outdoor/*"))[:70]),
):
    os.makedirs(folder, exist_ok=True)
    for i, f in enumerate(files):
        stem = os.path.basename(f).rsplit(".", 1)[0]
        out = f"{folder}/{i:02d}_{stem}.png" if folder == "calo" else f"{folder}/{stem}.png"  # calo/: in that order
        if os.path.exists(out):
            continue
        im = Image.open(f).convert("RGB")
        w, h = im.size
        s = min(w, h, 256)
        box = ((w - s) // 2, (h - s) // 2, (w - s) // 2 + s, (h - s) // 2 + s)
        im.crop(box).save(out)
