"""Built-in sample images (the demo's and the page's): three scikit-image photos and a generated line chart."""

from __future__ import annotations

import numpy as np
import torch
from skimage import data, transform

SAMPLE_SIZE = (192, 256)  # H, W of every sample
SAMPLES = ("astronaut", "coffee", "chelsea", "chart")  # the keys of sample_images(), in order


def line_chart() -> torch.Tensor:
    """A generated chart of straight lines: turbulence tilt shows as wavy lines.

    Returns:
        (3, H, W) float32 in [0, 1], (H, W) = ``SAMPLE_SIZE``.
    """
    h, w = SAMPLE_SIZE
    ys, xs = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    lines = ((ys % 16) < 2) | ((xs % 16) < 2)
    chart = torch.where(lines, 0.1, 0.9).float()
    return chart.expand(3, h, w).contiguous()


def sample_images() -> dict[str, torch.Tensor]:
    """Three skimage samples, centre-cropped to 4:3 and resized to ``SAMPLE_SIZE``, plus :func:`line_chart`.

    Returns:
        {name: (3, H, W) float32 in [0, 1]} with the names of ``SAMPLES``.
    """
    out = {}
    for name in SAMPLES[:3]:
        img = getattr(data, name)()
        h, w = img.shape[:2]
        ch, cw = (h, h * 4 // 3) if w * 3 >= h * 4 else (w * 3 // 4, w)
        y0, x0 = (h - ch) // 2, (w - cw) // 2
        img = transform.resize(img[y0 : y0 + ch, x0 : x0 + cw], SAMPLE_SIZE, anti_aliasing=True)
        out[name] = torch.from_numpy(np.asarray(img, dtype=np.float32)).permute(2, 0, 1).contiguous()
    out["chart"] = line_chart()
    return out
