"""Before/after pictures of a restoration (``d2turb restore --compare``): the input and the restored image side by side
at full resolution, each under its label. ``NAME_compare.png`` for an image; for a clip, the frames of
``NAME_compare.mp4`` and one ``NAME_compare.png``.

Output names follow one rule (docs/cli.md): an output is named after its input, ``NAME_<what>.<ext>``, where NAME
is the image's or video's file stem, or the folder's name for a folder clip (:func:`output_name`)."""

from __future__ import annotations

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from d2turb.io import to_uint8, write_image

LABELS = ("input", "restored")


def output_name(name: str, what: str, ext: str) -> str:
    """The one naming rule of restored outputs: ``NAME_restored.png``, ``NAME_restored.mp4``, ``NAME_compare.png``,
    ``NAME_compare.mp4``, ``NAME_fused.png``, ``NAME_bwd_flow_px.npy`` ... (``ext`` without dot; ``what`` is one word,
    or for a flow its direction, ``flow`` and its unit: ``bwd_flow_px`` / ``fwd_flow_px``, docs/flow.md)."""
    return f"{name}_{what}.{ext}"


def label_band(width: int) -> tuple[int, int]:
    """(font size, height of the label band above the panels) for panels ``width`` px wide: about 1/25 of the
    width, at least 12 px (readable on a 256 px frame and on a 1080p one alike)."""
    size = max(12, round(width / 25))
    return size, size + size // 2


def panel_gap(width: int) -> int:
    return max(4, width // 100)


def panel_origins(height: int, width: int, panels: int = 2) -> list[tuple[int, int]]:
    """(y, x) of each panel's top-left pixel in :func:`side_by_side`'s picture of ``height``×``width`` panels."""
    _, band = label_band(width)
    return [(band, k * (width + panel_gap(width))) for k in range(panels)]


def side_by_side(images: list, labels=LABELS) -> np.ndarray:
    """Panels (3,H,W) float tensors in [0,1] or (H,W,3) uint8 arrays, all of one size, left to right at full
    resolution on white, each labelled above its centre → (band+H, n·W + gaps, 3) uint8."""
    arrays = [to_uint8(im) if isinstance(im, torch.Tensor) else np.asarray(im, dtype=np.uint8) for im in images]
    h, w = arrays[0].shape[:2]
    if any(a.shape != arrays[0].shape for a in arrays):
        raise ValueError(f"panels differ in size: {[a.shape for a in arrays]}")
    size, band = label_band(w)
    origins = panel_origins(h, w, len(arrays))
    canvas = np.full((band + h, origins[-1][1] + w, 3), 255, np.uint8)
    for (y, x), arr in zip(origins, arrays):
        canvas[y : y + h, x : x + w] = arr
    picture = Image.fromarray(canvas)
    draw = ImageDraw.Draw(picture)
    font = ImageFont.load_default(size=size)
    for (_, x), text in zip(origins, labels):
        left, _, right, _ = draw.textbbox((0, 0), text, font=font)
        draw.text((x + (w - (right - left)) // 2, size // 5), text, fill=(0, 0, 0), font=font)
    return np.asarray(picture)


def save_compare(out_dir, name: str, before, after, png_level: int) -> None:
    """NAME_compare.png in ``out_dir``: input | restored, labelled (:func:`side_by_side`)."""
    write_image(out_dir / output_name(name, "compare", "png"), side_by_side([before, after]), png_level)
