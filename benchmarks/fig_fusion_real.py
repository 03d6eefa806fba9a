"""docs/images/fusion_real.jpg: the mean and the sharpest fusion on real clips, zoomed crops (docs/clips.md,
"Sharpest-coefficient fusion"): rows airport (heat shimmer), CLEAR hot air test3 (a number plate), DOST street (a
moving car: the ghost test, on the whole 1080p frame as ``restore`` sees it); columns the input frame, the mean
fusion, the sharpest fusion (``--deblur none``, window 16, frame 20; both with the moving-object fallback).

    PYTHONPATH=src python3 benchmarks/fig_fusion_real.py [--data ../shared/data/real] [--out FILE]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import av
import cv2
import numpy as np

from d2turb.clip import ClipRestorer
from d2turb.io import list_images, read_image

ROOT = Path(__file__).resolve().parents[1]
FRAME, TEMPORAL, FRAMES = 20, 16, 40


def _video(path: Path, n: int) -> list[np.ndarray]:
    with av.open(str(path)) as c:
        out = []
        for f in c.decode(video=0):
            out.append(f.to_ndarray(format="rgb24").astype(np.float32) / 255)
            if len(out) == n:
                break
    return out


def _folder(path: Path, n: int, crop=None) -> list[np.ndarray]:
    out = []
    for p in list_images(path)[:n]:
        img = read_image(p).permute(1, 2, 0).numpy()
        out.append(np.ascontiguousarray(img if crop is None else img[crop]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "real")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "images" / "fusion_real.jpg")
    a = ap.parse_args()
    clips = [  # name, frames, crop of the output shown (rows, cols), zoom
        ("airport", lambda: _folder(a.data / "airport_heat_shimmer", FRAMES), (slice(40, 200), slice(20, 220)), 2),
        (
            "test3",
            lambda: _video(a.data / "clear_hot_air" / "test3.mp4", FRAMES),
            (slice(300, 500), slice(350, 600)),
            1.6,
        ),
        (  # restored whole (the moving-object fallback judges the frame's residual against its whole scene)
            "dost",
            lambda: _folder(a.data / "dost_street_clip", FRAMES),
            (slice(520, 680), slice(700, 1030)),
            1.2,
        ),
    ]
    rows = []
    for name, load, crop, zoom in clips:
        frames = load()
        out = {}
        for fusion in ("mean", "sharpest"):
            for o in ClipRestorer(temporal=TEMPORAL, fusion=fusion).restore(frames):
                if o.index == FRAME:
                    out[fusion] = o.fused.permute(1, 2, 0).numpy()
        cells = [frames[FRAME][crop], out["mean"][crop], out["sharpest"][crop]]
        row = np.concatenate([np.pad(c, ((2, 2), (2, 2), (0, 0)), constant_values=1) for c in cells], 1)
        rows.append(cv2.resize(row, None, fx=zoom, fy=zoom, interpolation=cv2.INTER_CUBIC))
        print(name, flush=True)
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0)), constant_values=1) for r in rows]
    img = (np.clip(np.concatenate(rows, 0), 0, 1) * 255).round().astype(np.uint8)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(a.out), img[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])


if __name__ == "__main__":
    main()
