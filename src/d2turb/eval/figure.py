"""A readable labelled figure of image sections (the demo's): each section has a title, a label above every column
and a label (one or more lines) left of every row; rows may differ in height (zoomed crops under full frames)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from PIL import Image, ImageDraw, ImageFont

FONT, TITLE_FONT = 15, 19  # px
GAP = 6  # between cells
ROW_LABEL_W = 168  # the row labels' column


@dataclass
class Section:
    """``rows``: (label lines, cells) with cells HxWx3 uint8 arrays (None: an empty cell); all cells of a column share
    its width. ``columns``: one label per column."""

    title: str  # one line per line of text
    columns: list[str]
    rows: list[tuple[list[str], list]] = field(default_factory=list)


def _font(size: int):
    return ImageFont.load_default(size=size)


def _fit(draw, text: str, font, width: int) -> str:
    """``text`` cut (with …) to ``width`` px."""
    if draw.textlength(text, font=font) <= width:
        return text
    while text and draw.textlength(text + "…", font=font) > width:
        text = text[:-1]
    return text + "…"


def section_layout(section: Section) -> tuple[list[int], list[int], int]:
    """(column widths, row heights, header height) of a section."""
    widths = [
        max(c.shape[1] for _, cells in section.rows if (c := cells[j]) is not None) for j in range(len(section.columns))
    ]
    heights = [max(c.shape[0] for c in cells if c is not None) for _, cells in section.rows]
    return widths, heights, _title_height(section) + FONT + 8


def _title_height(section: Section) -> int:
    return len(section.title.splitlines()) * (TITLE_FONT + 6) + 4


def cell_origin(section: Section, row: int, col: int) -> tuple[int, int]:
    """(y, x) of the top-left pixel of a cell in :func:`render_section`'s picture."""
    widths, heights, header = section_layout(section)
    return header + sum(heights[:row]) + GAP * row, ROW_LABEL_W + sum(widths[:col]) + GAP * col


def render_section(section: Section) -> np.ndarray:
    widths, heights, header = section_layout(section)
    width = ROW_LABEL_W + sum(widths) + GAP * (len(widths) - 1)
    height = header + sum(heights) + GAP * (len(heights) - 1)
    canvas = Image.new("RGB", (width, height), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    font, bold = _font(FONT), _font(TITLE_FONT)
    for k, line in enumerate(section.title.splitlines()):
        draw.text((4, 2 + k * (TITLE_FONT + 6)), _fit(draw, line, bold, width - 8), fill=(0, 0, 0), font=bold)
    top = _title_height(section)
    for j, text in enumerate(section.columns):
        x = ROW_LABEL_W + sum(widths[:j]) + GAP * j
        label = _fit(draw, text, font, widths[j])
        draw.text((x + (widths[j] - draw.textlength(label, font=font)) / 2, top), label, fill=(0, 0, 0), font=font)
    for i, (lines, cells) in enumerate(section.rows):
        y0 = header + sum(heights[:i]) + GAP * i
        text_h = len(lines) * (FONT + 4)
        for k, line in enumerate(lines):
            draw.text(
                (6, y0 + (heights[i] - text_h) / 2 + k * (FONT + 4)),
                _fit(draw, line, font, ROW_LABEL_W - 10),
                fill=(0, 0, 0),
                font=font,
            )
        for j, cell in enumerate(cells):
            if cell is not None:
                y, x = cell_origin(section, i, j)
                canvas.paste(Image.fromarray(cell), (x, y))
    return np.asarray(canvas)


def stack(pictures: list[np.ndarray], gap: int = 18) -> np.ndarray:
    """Pictures one under the other on white, left-aligned, ``gap`` px apart."""
    width = max(p.shape[1] for p in pictures)
    height = sum(p.shape[0] for p in pictures) + gap * (len(pictures) - 1)
    canvas = np.full((height, width, 3), 255, np.uint8)
    y = 0
    for p in pictures:
        canvas[y : y + p.shape[0], : p.shape[1]] = p
        y += p.shape[0] + gap
    return canvas


def zoom(image: np.ndarray, box: tuple[int, int, int, int], factor: int = 2) -> np.ndarray:
    """The crop ``box`` = (x0, y0, x1, y1) of an HxWx3 uint8 image, enlarged ``factor``× with nearest pixels (every
    pixel shown as it is)."""
    x0, y0, x1, y1 = box
    return image[y0:y1, x0:x1].repeat(factor, axis=0).repeat(factor, axis=1)


def outline(image: np.ndarray, box: tuple[int, int, int, int], colour=(255, 210, 0)) -> np.ndarray:
    """A copy of ``image`` with a 1-px rectangle around ``box`` (where the zoomed crop comes from)."""
    x0, y0, x1, y1 = box
    out = image.copy()
    out[y0, x0:x1] = out[y1 - 1, x0:x1] = colour
    out[y0:y1, x0] = out[y0:y1, x1 - 1] = colour
    return out


def best_box(score: np.ndarray, size: tuple[int, int], step: int = 8) -> tuple[int, int, int, int]:
    """The ``size`` = (w, h) window (x0, y0, x1, y1) of the largest sum of the HxW map ``score``, on a ``step`` px
    grid: where a zoom shows what matters (the demo: where the restoration gains most)."""
    w, h = size
    integral = np.pad(np.asarray(score, dtype=np.float64).cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    best, box = -np.inf, (0, 0, w, h)
    for y in range(0, score.shape[0] - h + 1, step):
        for x in range(0, score.shape[1] - w + 1, step):
            total = integral[y + h, x + w] - integral[y, x + w] - integral[y + h, x] + integral[y, x]
            if total > best:
                best, box = total, (x, y, x + w, y + h)
    return box
