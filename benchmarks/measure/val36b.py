# issue 36 acceptance 1 and 2: N simulated clips of the test folder bsd100 drawn in the acceptance's ranges (λ/(D·ifov)
# 1-4 px and path 0.5-10 km log-uniform, D/r0 1-6, wind 0.5-4 m/s, boiling 0-0.3, camera noise σ 0-3 grey, JPEG
# quality 75-95; 32 frames of 160²), each measured three times: nothing given, the optics given (ifov and path), and
# the optics given with a random integer camera shake of ±3 px per frame (the clip simulated at 166² and each frame
# cropped at its own offset). One JSON line per clip (docs/measure.md, "Validation (issue 36)"). With PYTHONPATH=src
# and ../shared/data present: python3 val36b.py N [FIRST] > val36b.jsonl
import glob
import json
import sys

import cv2
import numpy as np

sys.path.insert(0, __import__("os").path.dirname(__file__))
from sim36 import clip, draw_case

from d2turb.clip import strength as M
from d2turb.errors import D2TurbError

SIZE, SHAKE = 160, 3


def jpeg(frame, quality):
    """(3,H,W) tensor in [0, 1] → the same after an 8-bit JPEG round trip at ``quality`` (OpenCV)."""
    img = np.rint(frame.permute(1, 2, 0).numpy() * 255).clip(0, 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    return cv2.imdecode(buf, cv2.IMREAD_UNCHANGED).astype(np.float32) / 255


def main():
    imgs = sorted(glob.glob("/work/shared/data/clean/bsd100/*_HR.png"))
    n = int(sys.argv[1])
    first = int(sys.argv[2]) if len(sys.argv) > 2 else 0
    labels = sys.argv[3].split(",") if len(sys.argv) > 3 else ["none", "all", "all_shake"]  # which measurements
    for i in range(first, first + n):
        rng = np.random.default_rng([36, i])  # per clip: any range of clips reproduces its own draws
        case = draw_case(rng)
        q, L, dr0, wind, boil, noise = (case[k] for k in ("q", "L", "dr0", "wind", "boil", "noise"))
        quality = int(rng.integers(75, 96))
        frames, p = clip(
            imgs[(7 * i) % len(imgs)],
            dr0,
            q,
            L,
            wind=wind,
            frames=32,
            size=SIZE + 2 * SHAKE,
            seed=100 + i,
            boil=boil,
            noise=noise,
        )
        frames = [jpeg(f, quality) for f in frames]  # (H,W,3) float32
        offsets = rng.integers(0, 2 * SHAKE + 1, (len(frames), 2))
        still = [f[SHAKE : SHAKE + SIZE, SHAKE : SHAKE + SIZE] for f in frames]
        shaken = [f[dy : dy + SIZE, dx : dx + SIZE] for f, (dy, dx) in zip(frames, offsets)]
        row = {"i": i, "dr0": dr0, "q": q, "L": L, "wind": wind, "boil": boil, "noise": noise, "jpeg": quality}
        for label, clip_frames, opt in (("none", still, None), ("all", still, p), ("all_shake", shaken, p)):
            if label not in labels:
                continue
            try:
                r = M.measure_clip(clip_frames, opt, bootstrap=50)
                lo, hi = r["dr0_ci"]
                row[label] = {"dr0": r["dr0"], "ci": r["dr0_ci"], "refused": bool(not lo > 0 or hi / lo > M.MAX_SPAN)}
                row[label].update(seeing=r["seeing_px"], seeing_ci=r["seeing_px_ci"])  # truth: q·D/r0
            except D2TurbError as e:
                row[label] = {"error": str(e)}
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
