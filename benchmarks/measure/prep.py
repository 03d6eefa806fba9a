# 256² centre crops of the clean images: cal/ (first 100 bsds500 images: a train folder, calibration only) and img/
# (first 70 bsd100 and all 69 sunhays_outdoor images: the test folders of the fixed split, validation only)
import glob
import os
import sys

from PIL import Image

C = sys.argv[1] if len(sys.argv) > 1 else "/work/shared/data/clean"
for folder, files in (
    ("cal", sorted(glob.glob(f"{C}/bsds500/*"))[:100]),
    ("img", sorted(glob.glob(f"{C}/bsd100/*.png"))[:70] + sorted(glob.glob(f"{C}/sunhays_outdoor/*"))[:70]),
):
    os.makedirs(folder, exist_ok=True)
    for f in files:
        out = f"{folder}/" + os.path.basename(f).rsplit(".", 1)[0] + ".png"
        if os.path.exists(out):
            continue
        im = Image.open(f).convert("RGB")
        w, h = im.size
        s = min(w, h, 256)
        box = ((w - s) // 2, (h - s) // 2, (w - s) // 2 + s, (h - s) // 2 + s)
        im.crop(box).save(out)
