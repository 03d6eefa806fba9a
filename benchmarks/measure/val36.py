# issue 36: N simulated clips drawn in the acceptance ranges, measured with nothing and with the optics given
# (docs/measure.md, "Validation (issue 36)"): python3 val36.py 12 > val36.jsonl
import glob
import json
import sys

import numpy as np

sys.path.insert(0, __import__("os").path.dirname(__file__))
from sim36 import clip, draw_case

from d2turb.clip import strength as M
from d2turb.errors import D2TurbError

imgs = sorted(glob.glob("/work/shared/data/clean/bsd100/*_HR.png"))
rng = np.random.default_rng(36)
n = int(sys.argv[1])
for i in range(n):
    case = draw_case(rng)
    q, L, dr0, wind, boil, noise = (case[k] for k in ("q", "L", "dr0", "wind", "boil", "noise"))
    frames, p = clip(
        imgs[(7 * i) % len(imgs)], dr0, q, L, wind=wind, frames=32, size=160, seed=100 + i, boil=boil, noise=noise
    )
    row = {"i": i, "dr0": dr0, "q": q, "L": L, "wind": wind, "boil": boil, "noise": noise}
    for label, opt in (("none", None), ("all", p)):
        try:
            r = M.measure_clip(frames, opt, bootstrap=50)
            row[label] = {"dr0": r["dr0"], "ci": r["dr0_ci"]}
        except D2TurbError as e:
            row[label] = {"refused": str(e)}
    print(json.dumps(row), flush=True)
