"""Check a depth estimate against measured KITTI depth: Spearman rank correlation on valid pixels.

``python -m d2turb.depth.evaluate [DEPTH_DATA_DIR]`` prints the table of docs/depth.md.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from d2turb.depth.prior import METHODS, estimate_depth_prior
from d2turb.io import read_image

KITTI_STEREO_FB = 721.5 * 0.54  # focal length (px) × baseline (m): depth = fb / disparity


def _read_uint16_over_256(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as img:
        return np.asarray(img).astype(np.float64) / 256.0


def kitti_cases(root: str | Path) -> list[tuple[Path, np.ndarray, np.ndarray]]:
    """[(rgb path, metric depth (H, W), valid mask)] from the shared depth folder (see its SOURCES.md)."""
    root = Path(root)
    cases = []
    for rgb in sorted((root / "kitti_metric3d" / "rgb").glob("*.png")):
        depth = _read_uint16_over_256(root / "kitti_metric3d" / "depth" / rgb.name)
        cases.append((rgb, depth, depth > 0))
    for rgb in sorted((root / "kitti2015_stereo" / "image_2").glob("*.png")):
        disp = _read_uint16_over_256(root / "kitti2015_stereo" / "disp_occ_0" / rgb.name)
        valid = disp > 0
        cases.append((rgb, np.where(valid, KITTI_STEREO_FB / np.where(valid, disp, 1.0), 0.0), valid))
    for depth_png in sorted((root / "kitti_lidar_sparse").glob("derived_sparse_depth_*_x256.png")):
        rgb = depth_png.parent / (depth_png.name.split("_")[3] + ".png")
        depth = _read_uint16_over_256(depth_png)
        cases.append((rgb, depth, depth > 0))
    return cases


def spearman_on_valid(estimate: torch.Tensor, truth: np.ndarray, valid: np.ndarray) -> float:
    from scipy.stats import spearmanr

    est = estimate.detach().cpu().reshape(truth.shape).numpy()
    return float(spearmanr(est[valid], truth[valid]).statistic)


def main(root: str = "../shared/data/depth") -> None:
    cases = kitti_cases(root)
    table = {m: [] for m in METHODS}
    print("| image | " + " | ".join(METHODS) + " |")
    print("|---" * (len(METHODS) + 1) + "|")
    for rgb, truth, valid in cases:
        image = read_image(rgb)
        row = [spearman_on_valid(estimate_depth_prior(image, m), truth, valid) for m in METHODS]
        for m, r in zip(METHODS, row):
            table[m].append(r)
        print(f"| {rgb.relative_to(Path(root)).as_posix()} | " + " | ".join(f"{r:.3f}" for r in row) + " |")
    print("| **mean** | " + " | ".join(f"**{np.mean(table[m]):.3f}**" for m in METHODS) + " |")


if __name__ == "__main__":
    main(*sys.argv[1:])
