"""The contact sheet of the real clips report (:mod:`d2turb.eval.real_clips`): per clip the columns input | mean
fusion | --deblur none | default, the sheet's frame whole with the crops outlined, then per crop of ``CROPS`` the
default's worst window for its measure zoomed, with its figure."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from d2turb.eval import artifacts
from d2turb.eval.real_clip_measures import COLUMNS, LABELS

CROP_PX = 160  # side of the zoomed crops (at most half the frame's shorter side)
ZOOM = 2  # nearest-neighbour zoom of the crops
PANEL_PX = 2 * CROP_PX  # width of each column of the sheet
# the sheet's crops, each the default's worst window for its measure (its colour on the whole frames)
CROPS = {
    "textured": ("most textured (input)", (255, 0, 0)),
    "tails": ("most near-black/white px added", (0, 160, 255)),
    "blocks": ("block grid most raised", (255, 160, 0)),
    "noise": ("most noise added in flat blocks", (0, 200, 0)),
    "sharpness": ("most sharpness lost at strong edges", (200, 0, 200)),
    "ghost": ("most edges absent from the input (ghost check)", (255, 255, 0)),
}


def _font(size: int):
    """DejaVu Sans from matplotlib (a dependency; it has λ and σ), else Pillow's default font."""
    try:
        import matplotlib

        return ImageFont.truetype(str(Path(matplotlib.get_data_path()) / "fonts" / "ttf" / "DejaVuSans.ttf"), size)
    except (ImportError, OSError):
        return ImageFont.load_default(size=size)


def crop_side(height: int, width: int) -> int:
    """Side of the zoomed crops: ``CROP_PX``, at most half the frame's shorter side, a multiple of 8 (the codec's
    grid stays on the crop's)."""
    return max(8, min(CROP_PX, min(height, width) // 2) // 8 * 8)


def _crop_caption(key: str, crop: np.ndarray, ref: np.ndarray, column: str) -> str:
    """The crop's own figure for its measure (against the input's crop)."""
    try:
        if key == "tails":
            black, white = artifacts.tail_fractions(crop)
            return f"black {100 * black:.1f} %, white {100 * white:.1f} %"
        if key == "blocks":
            return f"B/A {artifacts.block_energy(crop):.2f}"
        if key == "noise":
            return f"σ {255 * artifacts.flat_noise_sigma(crop, ref):.2f}"
        if key == "sharpness" or key == "textured":
            return f"sharpness {255 * artifacts.edge_sharpness(crop, ref):.1f}"
        if key == "ghost":
            return "" if column == "input" else f"ghost share {artifacts.ghost_share(crop, ref):.2f}"
    except ValueError:
        return ""
    return ""


def _whole(frame: np.ndarray, panel: int, boxes: list[tuple[int, int, int, tuple]]) -> Image.Image:
    """A frame scaled to ``panel`` px wide, each (y, x, side, colour) box outlined."""
    image = Image.fromarray(frame)
    scale = panel / image.width
    whole = image.resize((panel, max(1, round(image.height * scale))), Image.Resampling.LANCZOS)
    draw = ImageDraw.Draw(whole)
    for y, x, side, colour in boxes:
        draw.rectangle([x * scale, y * scale, (x + side) * scale - 1, (y + side) * scale - 1], outline=colour, width=2)
    return whole


def contact_sheet(
    frames: dict[str, np.ndarray],
    windows: dict[str, tuple[int, int]],
    side: int,
    title: str = "",
    shaken: dict[str, np.ndarray] | None = None,
    shaken_label: str = "",
) -> np.ndarray:
    """Columns input | mean fusion | --deblur none | default (``COLUMNS``): the sheet's frame (``frames``: {column:
    (H,W,3) uint8}) scaled to ``PANEL_PX`` wide with the crops outlined, then per crop of ``CROPS`` its ``side``²
    window ``windows[key]`` = (y, x) zoomed ×``ZOOM`` (nearest neighbour) with its figure; the ghost check's crop
    comes from the most shaken frame (``shaken``, shown whole above it; None: the sheet's frame) → (H, W, 3) uint8.
    """
    panel = max(PANEL_PX, side * ZOOM)
    font, small = _font(18), _font(14)
    band, caption, gap = 28, 20, 8
    shaken = frames if shaken is None else shaken
    ghost_frame = shaken is not frames
    rows: list[tuple[str, tuple | None, list]] = []  # (label, its box's colour, per column (caption, image))
    boxes = [(*windows[k], side, colour) for k, (_, colour) in CROPS.items() if k != "ghost" or not ghost_frame]
    rows.append(("", None, [("", _whole(frames[c], panel, boxes)) for c in COLUMNS]))
    for key, (label, colour) in CROPS.items():
        source = shaken if key == "ghost" else frames
        y, x = windows[key]
        if key == "ghost" and ghost_frame:
            yellow = [(y, x, side, CROPS["ghost"][1])]
            rows.append((shaken_label, None, [("", _whole(shaken[c], panel, yellow)) for c in COLUMNS]))
            label = f"{label}, that frame"
        cells = []
        for c in COLUMNS:
            crop = source[c][y : y + side, x : x + side]
            text = _crop_caption(key, crop, source["input"][y : y + side, x : x + side], c)
            zoomed = Image.fromarray(crop).resize((side * ZOOM, side * ZOOM), Image.Resampling.NEAREST)
            cells.append((text, zoomed))
        rows.append((f"{label} (y {y}, x {x})", colour, cells))
    heights = [
        (band if label else 0) + (caption if any(t for t, _ in cells) else 0) + max(i.height for _, i in cells) + gap
        for label, _, cells in rows
    ]
    top = 2 * band if title else band
    width = len(COLUMNS) * panel + (len(COLUMNS) - 1) * gap
    sheet = Image.new("RGB", (width, top + sum(heights)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    if title:
        draw.text((4, 4), title, fill=(0, 0, 0), font=font)
    for k, c in enumerate(COLUMNS):
        draw.text((k * (panel + gap) + 4, top - band + 4), LABELS[c], fill=(0, 0, 0), font=font)
    y0 = top
    for (label, colour, cells), height in zip(rows, heights, strict=True):
        row_y = y0
        if label:
            if colour is not None:
                draw.rectangle([4, row_y + 6, 20, row_y + 22], fill=colour, outline=(0, 0, 0))
            draw.text((28 if colour is not None else 4, row_y + 4), label, fill=(0, 0, 0), font=font)
            row_y += band
        if any(t for t, _ in cells):
            for k, (text, _) in enumerate(cells):
                draw.text((k * (panel + gap) + 4, row_y + 2), text, fill=(60, 60, 60), font=small)
            row_y += caption
        for k, (_, image) in enumerate(cells):
            sheet.paste(image, (k * (panel + gap) + (panel - image.width) // 2, row_y))
        y0 += height
    return np.asarray(sheet)
