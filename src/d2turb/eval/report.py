"""Evaluation reports: paper-style tables (Markdown and LaTeX, laid out like Table 1) and labelled
comparison grids (input | GT | each model)."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image, ImageDraw, ImageFont

from d2turb.sim.params import BINS

METRIC_INFO = {  # display name, higher is better, decimals
    "psnr": ("PSNR", True, 3),
    "ssim": ("SSIM", True, 3),
    "lpips": ("LPIPS", False, 3),
    "epe": ("EPE px", False, 3),  # flow end-point error vs the true backward flow ("input" = zero flow)
    "psnr_tilt": ("PSNR(Î_tilt)", True, 3),  # deblurring stage vs I_tilt
}
GROUPS = (*BINS, "avg")  # table columns: the D/r0 bins, then their mean


def _ranks(values: list[float | None], higher_better: bool, decimals: int) -> list[int | None]:
    """Rank (0 = best, 1 = second) of each value among the distinct rounded values; None for missing."""
    rounded = [None if v is None or math.isnan(v) else round(v, decimals) for v in values]
    distinct = sorted({v for v in rounded if v is not None}, reverse=higher_better)
    return [None if v is None else distinct.index(v) for v in rounded]


def _cells(table: dict, models: list[str], metric: str) -> list[list[tuple[str, int | None]]]:
    """Per model, per group: (formatted value, rank)."""
    _, higher, dec = METRIC_INFO[metric]
    out = [[("–", None)] * len(GROUPS) for _ in models]
    for g, group in enumerate(GROUPS):
        values = [table[m].get(metric, {}).get(group) for m in models]
        for i, (v, r) in enumerate(zip(values, _ranks(values, higher, dec))):
            if v is not None and not math.isnan(v):
                out[i][g] = (f"{v:.{dec}f}", r)
    return out


def markdown_table(table: dict, metrics: list[str]) -> str:
    """``table[model][metric][weak|medium|strong|avg]`` → Markdown table: rows = models, column groups =
    metric × {weak, medium, strong, Avg}; best in **bold**, second <u>underlined</u> (as in Table 1)."""
    models = list(table)
    head = ["Method"]
    for metric in metrics:
        name, higher, _ = METRIC_INFO[metric]
        arrow = "↑" if higher else "↓"
        head += [f"{name}{arrow} weak", "medium", "strong", "**Avg**"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" + "---:|" * (len(head) - 1)]
    per_metric = {metric: _cells(table, models, metric) for metric in metrics}
    for i, model in enumerate(models):
        row = [model]
        for metric in metrics:
            for text, rank in per_metric[metric][i]:
                row.append(f"**{text}**" if rank == 0 and len(models) > 1 else f"<u>{text}</u>" if rank == 1 else text)
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


def latex_table(table: dict, metrics: list[str]) -> str:
    """The same table as LaTeX (booktabs, \\textbf best, \\underline second), like the paper's Table 1."""
    models = list(table)
    n = 4 * len(metrics)
    head = " & ".join(
        rf"\multicolumn{{4}}{{c}}{{{METRIC_INFO[m][0]}$\{'uparrow' if METRIC_INFO[m][1] else 'downarrow'}$}}"
        for m in metrics
    )
    rules = " ".join(rf"\cmidrule(lr){{{2 + 4 * k}-{5 + 4 * k}}}" for k in range(len(metrics)))
    sub = " & ".join([r"weak & medium & strong & \textbf{Avg}"] * len(metrics))
    lines = [
        rf"\begin{{tabular}}{{@{{}} l *{{{n}}}{{c}} @{{}}}}",
        r"\toprule",
        rf"\multirow{{2}}{{*}}{{Method}} & {head} \\",
        rules,
        rf"& {sub} \\",
        r"\midrule",
    ]
    per_metric = {metric: _cells(table, models, metric) for metric in metrics}
    for i, model in enumerate(models):
        cells = []
        for metric in metrics:
            for text, rank in per_metric[metric][i]:
                text = text.replace("–", "--")
                cells.append(
                    rf"\textbf{{{text}}}"
                    if rank == 0 and len(models) > 1
                    else rf"\underline{{{text}}}"
                    if rank == 1
                    else text
                )
        name = model.replace("_", r"\_")
        lines.append(f"{name} & " + " & ".join(cells) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}"]
    return "\n".join(lines) + "\n"


def flow_to_rgb(flow: torch.Tensor, max_px: float | None = None) -> torch.Tensor:
    """Colour-wheel picture of a flow field: hue = direction (+x red, +y chartreuse, −x cyan, −y violet),
    saturation = magnitude / ``max_px`` (default: the largest magnitude), white = no motion.

    Shape: flow (2, H, W) in pixels, x then y -> (3, H, W) float in [0, 1].
    """
    from matplotlib.colors import hsv_to_rgb

    if flow.ndim != 3 or flow.shape[0] != 2:
        raise ValueError(f"flow_to_rgb: expected a (2, H, W) flow, got {tuple(flow.shape)}")
    f = flow.detach().float().cpu()
    mag = f.norm(dim=0)
    scale = float(mag.max()) if max_px is None else float(max_px)
    hue = (torch.atan2(f[1], f[0]) / (2 * math.pi)) % 1.0
    sat = (mag / scale).clamp(0, 1) if scale > 0 else torch.zeros_like(mag)
    hsv = torch.stack([hue, sat, torch.ones_like(mag)], dim=-1).numpy()
    return torch.from_numpy(hsv_to_rgb(hsv)).permute(2, 0, 1).float()


def fit_cell(image: torch.Tensor, cell: int) -> torch.Tensor:
    """(3,H,W) in [0,1] → resized (area) so that its longer side is ``cell`` (never enlarged)."""
    h, w = image.shape[-2:]
    scale = min(1.0, cell / max(h, w))
    if scale == 1.0:
        return image.float()
    size = (max(1, round(h * scale)), max(1, round(w * scale)))
    return F.interpolate(image[None].float(), size=size, mode="area")[0]


def comparison_grid(
    rows: list[list[torch.Tensor]], col_labels: list[str], row_labels: list[str], cell: int = 192, gap: int = 4
) -> np.ndarray:
    """Labelled grid (HxWx3 uint8): one row per sample, one column per image kind. Each image is fitted
    into a ``cell``×``cell`` box (top-left aligned; the box shrinks to the largest image when all are
    smaller), column labels on top, row labels on the left."""
    cell = min(cell, max(max(im.shape[-2:]) for images in rows for im in images))
    font = ImageFont.load_default()
    label_w = _row_label_width(row_labels, gap)
    n_cols = len(col_labels)
    width = label_w + n_cols * (cell + gap)
    height = _LABEL_H + len(rows) * (cell + gap)
    canvas = Image.new("RGB", (width, height), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for j, text in enumerate(col_labels):
        draw.text((label_w + j * (cell + gap) + 2, 3), text, fill=(0, 0, 0), font=font)
    for i, (images, text) in enumerate(zip(rows, row_labels)):
        top, _ = _cell_origin(i, 0, label_w, cell, gap)
        draw.text((gap, top + cell // 2 - 6), text, fill=(0, 0, 0), font=font)
        for j, image in enumerate(images):
            arr = (fit_cell(image, cell).clamp(0, 1).permute(1, 2, 0).numpy() * 255.0).round().astype(np.uint8)
            y, x = _cell_origin(i, j, label_w, cell, gap)
            canvas.paste(Image.fromarray(arr), (x, y))
    return np.asarray(canvas)


_LABEL_H = 18  # the column labels' band at the top of a comparison grid


def _row_label_width(row_labels: list[str], gap: int) -> int:
    font = ImageFont.load_default()
    return max([int(font.getlength(t)) for t in row_labels] + [0]) + 2 * gap


def _cell_origin(row: int, col: int, label_w: int, cell: int, gap: int) -> tuple[int, int]:
    return _LABEL_H + row * (cell + gap), label_w + col * (cell + gap)


def grid_cell_origin(row: int, col: int, row_labels: list[str], cell: int = 192, gap: int = 4) -> tuple[int, int]:
    """(y, x) of the top-left pixel of a cell in :func:`comparison_grid`'s output (``cell``: the size it drew
    cells at, after shrinking to the largest image)."""
    return _cell_origin(row, col, _row_label_width(row_labels, gap), cell, gap)
