# issue 36: calibration clips for the interval's widening outside the gain table's box (docs/measure.md, "Outside
# the calibrated box"): N simulated clips of the TRAIN folder bsds500 (never the test folders of val36b.py) drawn in
# the acceptance's ranges as val36b.py draws them, measured with the optics given. One JSON line per clip: the truth,
# the estimate, the interval's log-sds and the quantities the widening reads (the estimate's tilt rms in px, the
# footprint in px). With PYTHONPATH=src and ../shared/data present: python3 cal36.py N > cal36.jsonl
import glob
import json
import math
import sys

import numpy as np

sys.path.insert(0, __import__("os").path.dirname(__file__))
from sim36 import clip, draw_case
from val36b import SIZE, jpeg

from d2turb.clip import strength as M
from d2turb.errors import D2TurbError

imgs = sorted(glob.glob("/work/shared/data/clean/bsds500/*.jpg"))
n = int(sys.argv[1])
for i in range(n):
    rng = np.random.default_rng([3600, i])
    case = draw_case(rng)
    q, L, dr0, wind, boil, noise = (case[k] for k in ("q", "L", "dr0", "wind", "boil", "noise"))
    quality = int(rng.integers(75, 96))
    frames, p = clip(
        imgs[(13 * i) % len(imgs)], dr0, q, L, wind=wind, frames=32, size=SIZE, seed=500 + i, boil=boil, noise=noise
    )
    frames = [jpeg(f, quality) for f in frames]
    row = {"i": i, "dr0": dr0, "q": q, "L": L, "footprint_px": p.aperture_m**2 * q / (p.wavelength_m * L)}
    try:
        r = M.measure_clip(frames, p, bootstrap=50)
        row.update(
            est=r["dr0"],
            ci=r["dr0_ci"],
            log_sd=r["dr0_log_sd"],
            tilt_rms_px=math.sqrt(r["tilt_var_px2"]),
        )
    except D2TurbError as e:
        row["error"] = str(e)
    print(json.dumps(row), flush=True)
