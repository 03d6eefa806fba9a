"""docs/images/clip_airport_niqe.jpg: one airport frame, a light denoise of it, the clip restoration and the
single-frame filter, each labelled with its NIQE (docs/clips.md, "What NIQE says about clip restoration").

    PYTHONPATH=src python3 benchmarks/fig_clip_airport_niqe.py [--data ../shared/data/real] [--out FILE]

D/r0 5.43 is the airport clip's estimate from its registration (benchmarks/results/clip_real_niqe.json), what
``restore --deblur auto`` uses there.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import torch
from PIL import Image

from d2turb.clip import ClipRestorer, PhysicsDeblur
from d2turb.eval.niqe import niqe
from d2turb.eval.report import comparison_grid
from d2turb.io import list_images, read_image, to_uint8

ROOT = Path(__file__).resolve().parents[1]
DR0, FRAME = 5.43, 24


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "real")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "images" / "clip_airport_niqe.jpg")
    args = ap.parse_args()
    frames = [read_image(f) for f in list_images(args.data / "airport_heat_shimmer")[:64]]
    deblur = PhysicsDeblur(DR0)
    outputs = ClipRestorer(temporal=32, deblur=deblur).restore(frames)
    restored = next(out.restored for out in outputs if out.index == FRAME)
    frame = frames[FRAME]
    denoised = cv2.fastNlMeansDenoisingColored(to_uint8(frame), None, 3, 3, 7, 21)
    denoised = torch.from_numpy(denoised / 255.0).permute(2, 0, 1)
    images = {
        "input": frame,
        "input, NL-means h 3": denoised.float(),
        "clip: fused + physics": restored,
        "single frame + physics": deblur(frame),
    }
    labels = [f"{name} (NIQE {float(niqe(image)):.1f})" for name, image in images.items()]
    grid = comparison_grid([list(images.values())], labels, [f"airport, frame {FRAME}"], cell=220)
    Image.fromarray(grid).save(args.out, quality=88)
    print(args.out, labels)


if __name__ == "__main__":
    main()
