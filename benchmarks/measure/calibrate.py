# registration gain: DIS-measured / true differential-tilt power per separation, on the calibration clips (cal_*)
import glob
import json

import numpy as np

from d2turb import measure as M
from d2turb.io import list_images, read_image

rows = []
for d in sorted(glob.glob("clips/cal_*")):
    if d.endswith(".err"):
        continue
    meta = json.load(open(f"{d}/meta.json"))
    frames = [read_image(f) for f in list_images(f"{d}/turb")]
    true = np.stack([np.load(f) for f in sorted(glob.glob(f"{d}/flow/*.npy"))]).transpose(0, 2, 3, 1)
    gray, crop = M._crop(M._gray_frames(frames), 320)
    flows, mask, diag = M.register_clip(gray)
    seps = [8, 16, 32, 64]
    nd, pd_, ser = M.lag_sums(flows, mask, seps)
    nt, pt, _ = M.lag_sums(true, mask, seps)
    gain = {}
    for r in seps:
        js = [j for j, s in enumerate(ser) if s[0] == r]
        gain[r] = float(
            sum(nd[:, j, 1:].sum() / pd_[:, j].sum() for j in js) / sum(nt[:, j, 1:].sum() / pt[:, j].sum() for j in js)
        )
    rows.append({"clip": d, "dr0": meta["dr0"], "gain": gain, "valid": diag["valid_fraction"]})
    print(json.dumps(rows[-1]), flush=True)
json.dump(rows, open("gain.json", "w"), indent=1)
