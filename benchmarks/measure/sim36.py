# issue 36: simulated clips of known optics for the unknown-optics validation (docs/measure.md); run with
# PYTHONPATH=src and ../shared/data present. `python3 sim36.py` measures three clips (none, path, ifov, all given).
import glob
import time

import numpy as np
import torch

from d2turb.clip import strength as M
from d2turb.io import read_image
from d2turb.sim import Simulator, TurbulenceParams


def draw_case(rng, q=(1.0, 4.0), L=(500.0, 10000.0), dr0=(1.0, 6.0)) -> dict:
    """One clip's turbulence and optics drawn in issue 36's acceptance ranges (or the ranges given), in this order from
    ``rng``: λ/(D·ifov) ``q`` 1-4 px and path ``L`` 0.5-10 km log-uniform, ``dr0`` 1-6, ``wind`` 0.5-4 m/s, ``boil``
    0-0.3, camera ``noise`` σ 0-3 grey levels (val36.py, val36b.py, cal36.py; val53.py with issue 53's ranges)."""
    return {
        "q": float(np.exp(rng.uniform(np.log(q[0]), np.log(q[1])))),
        "L": float(np.exp(rng.uniform(np.log(L[0]), np.log(L[1])))),
        "dr0": float(rng.uniform(*dr0)),
        "wind": float(rng.uniform(0.5, 4)),
        "boil": float(rng.uniform(0, 0.3)),
        "noise": float(rng.uniform(0, 3)),
    }


def clip(img_path, dr0, q=2.0, L=1000.0, wind=2.0, frames=32, size=192, seed=0, boil=0.1, noise=0.0):
    img = read_image(img_path)
    _, h, w = img.shape
    y0, x0 = (h - size) // 2, (w - size) // 2
    img = img[:, y0 : y0 + size, x0 : x0 + size]
    lam, D = 525e-9, 0.1
    p = TurbulenceParams(aperture_m=D, wavelength_m=lam, path_length_m=L, dr0=dr0, ifov_rad=lam / (D * q))
    sim = Simulator(p)
    g = torch.Generator().manual_seed(seed)
    out = []
    rng = np.random.default_rng(seed)
    for r in sim.sequence(img, frames=frames, wind=wind, boil=boil, generator=g):
        f = r.turb[0].clamp(0, 1).numpy()
        if noise:
            f = np.clip(f + rng.normal(0, noise / 255, f.shape), 0, 1).astype(np.float32)
        out.append(torch.from_numpy(f))
    return out, p


if __name__ == "__main__":
    imgs = sorted(glob.glob("/work/shared/data/clean/bsd100/*_HR.png"))
    for k, (dr0, q, L) in enumerate([(2.0, 2.0, 1000.0), (4.0, 2.0, 1000.0), (2.0, 3.0, 3000.0)]):
        t = time.time()
        frames, p = clip(imgs[k], dr0, q, L, seed=k)
        t1 = time.time()
        for opt in (None, {"path_length_m": L}, {"ifov_rad": p.ifov_rad}, p):
            try:
                r = M.measure_clip(frames, opt, bootstrap=50)
                print(
                    dr0,
                    q,
                    L,
                    "opt" if opt is None else type(opt).__name__,
                    round(r["dr0"], 2),
                    [round(x, 2) for x in r["dr0_ci"]],
                    r["widened_by"],
                    r.get("blur"),
                    round(r["lambda_over_d_px"], 2),
                    r["fit"]["footprint_px"],
                )
            except Exception as e:
                print("ERR", e)
        print("times", round(t1 - t, 1), round(time.time() - t1, 1), flush=True)
