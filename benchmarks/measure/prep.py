# 256² centre crops: cal/ (first 8 bsds500 images) and img/ (first 12 bsd100 and 12 sunhays_outdoor images)
import glob
import os

from PIL import Image

C = "/work/shared/data/clean"
for folder, files in (
    ("cal", sorted(glob.glob(f"{C}/bsds500/*"))[:8]),
    ("img", sorted(glob.glob(f"{C}/bsd100/*.png"))[:12] + sorted(glob.glob(f"{C}/sunhays_outdoor/*"))[:12]),
):
    os.makedirs(folder, exist_ok=True)
    for f in files:
        im = Image.open(f).convert("RGB")
        w, h = im.size
        s = min(w, h, 256)
        box = ((w - s) // 2, (h - s) // 2, (w - s) // 2 + s, (h - s) // 2 + s)
        im.crop(box).save(f"{folder}/" + os.path.basename(f).rsplit(".", 1)[0] + ".png")
