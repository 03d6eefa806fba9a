# issue 53 acceptance 3: flat crops (under 2 % textured area) are refused with the cause. Four flat 320² scenes of 64
# frames through the simulator as val53.py makes its clips (D/r0 3, λ/(D·ifov) 2 px, path 1 km, noise σ 1 grey, JPEG
# 90): a constant grey, a sky-like gradient, a bsd100 test image at 1 % of its contrast, the same image blurred by a
# Gaussian of σ 20 px. Each measured with nothing given and with --ifov and --path-length; one JSON line per scene
# with the refusal (or the estimate) and the registration's textured fraction. With PYTHONPATH=src and ../shared/data
# present: python3 flat53.py > flat53.jsonl
import glob
import json
import sys

import cv2
import numpy as np
import torch

sys.path.insert(0, __import__("os").path.dirname(__file__))
from val36b import jpeg

from d2turb.clip import strength as M
from d2turb.errors import D2TurbError
from d2turb.io import read_image
from d2turb.sim import Simulator, TurbulenceParams

SIZE, FRAMES = 320, 64


def scenes() -> dict:
    img = read_image(sorted(glob.glob("/work/shared/data/clean/bsd100/*_HR.png"))[3])[:, :SIZE, :SIZE].numpy()
    ramp = np.linspace(0.45, 0.7, SIZE, dtype=np.float32)[:, None].repeat(SIZE, 1)
    blurred = np.stack([cv2.GaussianBlur(c, (0, 0), 20) for c in img])
    return {
        "constant": np.full((3, SIZE, SIZE), 0.6, np.float32),
        "gradient": np.stack([ramp, ramp * 1.05, ramp * 1.2]).clip(0, 1),
        "low_contrast": (0.5 + 0.01 * (img - img.mean())).astype(np.float32),
        "blurred": blurred.astype(np.float32),
    }


def main():
    torch.set_num_threads(1)
    lam, aperture, q = 525e-9, 0.1, 2.0
    p = TurbulenceParams(
        aperture_m=aperture, wavelength_m=lam, path_length_m=1000.0, dr0=3.0, ifov_rad=lam / (aperture * q)
    )
    for k, (name, scene) in enumerate(scenes().items()):
        rng = np.random.default_rng([5353, k])
        seq = Simulator(p).sequence(
            torch.from_numpy(scene), frames=FRAMES, wind=2.0, boil=0.1, generator=torch.Generator().manual_seed(k)
        )
        frames = []
        for r in seq:
            f = r.turb[0].clamp(0, 1).numpy()
            frames.append(torch.from_numpy(np.clip(f + rng.normal(0, 1 / 255, f.shape), 0, 1).astype(np.float32)))
        frames = [jpeg(f, 90) for f in frames]
        row = {"scene": name}
        for label, opt in (("none", None), ("ifov_path", {"ifov_rad": p.ifov_rad, "path_length_m": 1000.0})):
            try:
                r = M.measure_clip(frames, opt, bootstrap=20)
                row[label] = {
                    "textured": r["textured_fraction"],
                    "valid": r["valid_fraction"],
                    "seeing_px": r["seeing_px"],
                }
            except D2TurbError as e:
                row[label] = {"error": str(e)}
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
