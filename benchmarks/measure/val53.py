# issue 53 acceptance 1-3: N simulated clips of the TEST folder bsd100 (320², 64 frames) drawn in the acceptance's
# ranges (λ/(D·ifov) 1.5-3 px and path 0.5-3 km log-uniform, D/r0 1.5-4.5 uniform; wind 0.5-4 m/s, boiling 0-0.3,
# camera noise σ 0-3 grey, JPEG quality 75-95 as in val36b.py), each measured twice: nothing given, and --ifov with
# --path-length given (aperture and wavelength at the simulator's, the defaults). One JSON line per clip with the truth
# (ρ = λ/(D·ifov)·D/r0 and D/r0) and each measurement's estimate and 90 % intervals, or its refusal
# (docs/measure.md, "Validation (issue 53)"; table53.py summarises). With PYTHONPATH=src and ../shared/data present:
# python3 val53.py N [FIRST [LABELS]] > val53.jsonl (LABELS: none,ifov_path by default)
import glob
import json
import sys

import numpy as np
import torch

sys.path.insert(0, __import__("os").path.dirname(__file__))
from sim36 import clip, draw_case
from val36b import jpeg

from d2turb.clip import strength as M
from d2turb.errors import D2TurbError

SIZE, FRAMES = 320, 64


def draw_case53(rng) -> dict:
    """One clip's turbulence and optics in issue 53's acceptance ranges, in this order from ``rng``: sim36's draw in
    λ/(D·ifov) 1.5-3 px, path 0.5-3 km, D/r0 1.5-4.5, then the JPEG quality 75-95."""
    case = draw_case(rng, q=(1.5, 3.0), L=(500.0, 3000.0), dr0=(1.5, 4.5))
    return {**case, "jpeg": int(rng.integers(75, 96))}


def summary(r: dict) -> dict:
    keys = ("seeing_px", "seeing_px_ci", "dr0", "dr0_ci", "lambda_over_d_px", "widened_by")
    out = {k: r[k] for k in keys if k in r}
    out.update(valid=r["valid_fraction"], textured=r["textured_fraction"], footprint_px=r["fit"]["footprint_px"])
    out.update(blur_used=r["parameters"]["blur_used"], narrowing=r["narrowing"])
    return out


def main():
    torch.set_num_threads(1)
    imgs = sorted(glob.glob("/work/shared/data/clean/bsd100/*_HR.png"))
    n = int(sys.argv[1])
    first = int(sys.argv[2]) if len(sys.argv) > 2 else 0
    labels = sys.argv[3].split(",") if len(sys.argv) > 3 else ["none", "ifov_path"]  # which measurements
    for i in range(first, first + n):
        rng = np.random.default_rng([53, i])  # per clip: any range of clips reproduces its own draws
        c = draw_case53(rng)
        img = imgs[(7 * i) % len(imgs)]
        frames, p = clip(img, c["dr0"], c["q"], c["L"], c["wind"], FRAMES, SIZE, 5300 + i, c["boil"], c["noise"])
        frames = [jpeg(f, c["jpeg"]) for f in frames]
        row = {"i": i, "image": img.rsplit("/", 1)[-1], **c, "rho": c["q"] * c["dr0"]}
        given = {"ifov_rad": p.ifov_rad, "path_length_m": p.path_length_m}
        for label, opt in (("none", None), ("ifov_path", given)):
            if label not in labels:
                continue
            try:
                row[label] = summary(M.measure_clip(frames, opt, bootstrap=50))
            except D2TurbError as e:
                row[label] = {"error": str(e)}
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
