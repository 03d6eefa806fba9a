"""What the page shows besides the command's own files: downscaled pictures, the flow as a colour wheel, the
derived quantities and NIQE as Markdown tables. Written under the run's ``views/`` folder."""

from __future__ import annotations

from pathlib import Path

import torch

from d2turb.errors import D2TurbError
from d2turb.eval.niqe import niqe
from d2turb.eval.report import fit_cell, flow_to_rgb
from d2turb.io import write_image

PREVIEW_SIDE = 2048  # pictures shown in the page are downscaled to this longer side (downloads keep full size)

# what a no-reference score is worth (docs/metrics.md, "What NIQE and PIQE show, and what they do not")
NIQE_CAVEAT = (
    "NIQE compares image statistics with clean photos, not with the scene: a hint, not proof of restoration "
    "(a broken model's output can score better than its input; judge by the pictures, see docs/metrics.md)."
)


def preview(image: torch.Tensor, path: Path, source: Path | None = None) -> Path:
    """(C,H,W) in [0,1] as an 8-bit PNG for the page, downscaled to PREVIEW_SIDE if larger; ``source``: a PNG
    that already holds this image, returned as is when no downscaling is needed."""
    if max(image.shape[-2:]) <= PREVIEW_SIDE:
        if source is not None:
            return source
        write_image(path, image)
    else:
        write_image(path, fit_cell(image.float(), PREVIEW_SIDE))
    return path


def flow_view(flow: torch.Tensor, path: Path) -> tuple[Path, float]:
    """Colour-wheel picture of a (2,H,W) flow with the wheel as a legend in the bottom-right corner; returns the
    path and the magnitude (px) that maps to full saturation."""
    scale = float(flow.norm(dim=0).max())
    rgb = flow_to_rgb(flow, max_px=scale if scale > 0 else 1.0)
    h, w = rgb.shape[-2:]
    r = max(8, min(h, w) // 8)
    if min(h, w) >= 4 * r:
        ys, xs = torch.meshgrid(torch.arange(2 * r + 1) - r, torch.arange(2 * r + 1) - r, indexing="ij")
        wheel = flow_to_rgb(torch.stack([xs, ys]).float(), max_px=float(r))
        inside = (xs**2 + ys**2) <= r * r
        patch = rgb[:, h - 2 * r - 3 : h - 2, w - 2 * r - 3 : w - 2]  # bottom right
        patch.copy_(torch.where(inside, wheel, patch))
    return preview(rgb, path), scale


# ---- derived quantities (d2turb.sim.derived_quantities) ------------------------------------------------------
_DERIVED_ROWS = (
    ("dr0", "D/r0", "{:.3g}", ""),
    ("bin", "strength bin", "{}", ""),
    ("r0_m", "Fried parameter r0", "{:.3g}", "m"),
    ("cn2", "Cn² (constant along the path)", "{:.3g}", "m^-2/3"),
    ("theta0_urad", "isoplanatic angle θ0", "{:.3g}", "µrad"),
    ("theta0_px", "θ0 in pixels", "{:.3g}", "px"),
    ("tilt_sigma_px", "tilt σ per axis (M = 1)", "{:.3g}", "px"),
    ("tilt_sigma_px_mean_m", "tilt σ at the mean M", "{:.3g}", "px"),
    ("mean_modulation", "mean modulation M", "{:.3g}", ""),
    ("footprint_px", "aperture footprint D/(ifov·L)", "{:.3g}", "px"),
    ("samples_per_lambda_d", "pixels per λ/D (2 = Nyquist)", "{:.3g}", ""),
    ("ifov_urad", "pixel IFOV", "{:.4g}", "µrad"),
)


def derived_markdown(d: dict) -> str:
    lines = ["| quantity | value |", "|---|---|"]
    for key, label, form, unit in _DERIVED_ROWS:
        if key in d:
            lines.append(f"| {label} | {form.format(d[key])} {unit} |")
    return "\n".join(lines)


# ---- NIQE ------------------------------------------------------------------------------------------------------
def niqe_or_reason(image: torch.Tensor) -> float | str:
    """NIQE of ``image``, or "n/a (why)" where it has none (too small, too flat)."""
    try:
        return float(niqe(image))
    except D2TurbError as exc:
        return f"n/a ({exc})"


def niqe_markdown(values: dict) -> str:
    def cell(v):
        return f"{v:.3f}" if isinstance(v, float) else str(v)

    return (
        "| NIQE (lower is better) | value |\n|---|---|\n"
        f"| input | {cell(values['input'])} |\n| restored | {cell(values['restored'])} |\n\n{NIQE_CAVEAT}"
    )
