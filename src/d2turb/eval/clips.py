"""Clip restoration on a sequence dataset (``make-dataset --frames N``), per strength bin: PSNR/SSIM of the input
frame, the plain temporal mean, the registered fusion and the fusion after each deblur option; end-point error of
the estimated displacement against the observable flow (the simulator's flow minus its temporal mean: a clip
cannot see its own mean tilt) and against zero. Beside the plain PSNR/SSIM, the same with each frame's global
sub-pixel offset against the clean image removed (``remove_global_offset``): a clip sees no tilt that stays put over
it, so its output keeps the window's mean tilt, which plain PSNR punishes as if it were a restoration error. And
CW-SSIM (:mod:`d2turb.eval.cwssim`), the field's shift-tolerant score, of the plain frames. docs/clips.md.

Field-realistic clips (``make-dataset --profile field``) hold the truth of every frame (camera shake, moving
objects): each output frame is scored against its own frame's truth, and inside the moving objects' boxes as well
(``"<row> box_psnr"``, ``box_psnr_aligned``: the PSNR of the pixels inside each box of each scored frame, averaged over
boxes; the input row is the input frame's score in the same boxes)."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage
from skimage.registration import phase_cross_correlation

from d2turb.clip import ClipRestorer, PhysicsDeblur
from d2turb.clip.blind import BlindDeblur
from d2turb.clip.live import DEFAULT_PRESET, LiveRestorer, dis_preset, live_deblurred
from d2turb.clip.pipeline import deblurred
from d2turb.data.sequence import SequenceDataset
from d2turb.defaults import DEFAULT_FUSION, MEASURED_TEMPORAL
from d2turb.errors import D2TurbError
from d2turb.eval.cwssim import cw_ssim
from d2turb.eval.metrics import KeyedMean, end_point_error, psnr, ssim
from d2turb.io import write_json, write_text
from d2turb.models.hub import resolve_weights
from d2turb.restore.single import Restorer
from d2turb.sim import TurbulenceParams, depth_modulation
from d2turb.sim.params import BINS

ROWS = ("input", "temporal mean", "fused")
MIN_BOX_PX = 64  # boxes with fewer pixels inside the scored area (the frame's edge cuts them) are not scored
OFFSET_MARGIN_PX = 8  # border left out of the offset-removed scores (at most 1/8 of the side): shifts replicate it
MAX_OFFSET_PX = 6.0  # larger estimated offsets are not removed (a failed correlation, not a mean tilt)


def remove_global_offset(image: torch.Tensor, reference: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, tuple]:
    """(image shifted by its global sub-pixel offset onto ``reference``, reference, (dy, dx)), both cropped by
    ``OFFSET_MARGIN_PX``. The offset is the least-squares one of their greys inside the margin (the offset-removed
    PSNR is then the best PSNR over global shifts): started at the peak of the phase correlation of Hann-windowed
    greys (skimage ``phase_cross_correlation``, whole pixels), refined by Gauss–Newton steps
    s ← s − (JᵀJ)⁻¹Jᵀ(ref − image(x − s)), J the gradient of the shifted image (5 steps or until a step is under
    0.002 px); shifts are cubic splines (scipy ``ndimage``). Offsets above ``MAX_OFFSET_PX`` are not removed.
    Shape: (C, H, W) each."""
    luma = torch.tensor([0.299, 0.587, 0.114], dtype=torch.float64)[:, None, None]
    grey = [
        (x.double() * luma).sum(0).numpy() if x.shape[0] == 3 else x[0].double().numpy() for x in (image, reference)
    ]
    m = max(1, min(OFFSET_MARGIN_PX, min(grey[0].shape) // 8))  # small test images keep most of their area
    inner = (slice(m, -m), slice(m, -m))
    window = np.outer(np.hanning(grey[0].shape[0]), np.hanning(grey[0].shape[1]))
    shift, _, _ = phase_cross_correlation(grey[1] * window, grey[0] * window)
    shift = shift.astype(np.float64) if np.abs(shift).max() <= MAX_OFFSET_PX else np.zeros(2)
    coeffs = ndimage.spline_filter(grey[0], order=3, mode="nearest")  # once, not per step
    ref = grey[1][inner]
    for _ in range(5):
        moved = ndimage.shift(coeffs, shift, order=3, mode="nearest", prefilter=False)
        gy, gx = np.gradient(moved)
        j = np.stack([gy[inner].ravel(), gx[inner].ravel()], 1)
        # d/ds image(x − s) = −∇: ref − image(x − s − δ) ≈ (ref − moved) + J·δ, least squares δ = −J⁺(ref − moved)
        step = -np.linalg.lstsq(j, (ref - moved[inner]).ravel(), rcond=None)[0]
        shift = shift + step
        if np.abs(step).max() < 0.002:
            break
    if not np.all(np.isfinite(shift)) or np.abs(shift).max() > MAX_OFFSET_PX:
        shift = np.zeros(2)
    moved = np.stack([ndimage.shift(c, shift, order=3, mode="nearest") for c in image.double().numpy()])
    crop = (slice(None), *inner)
    return torch.from_numpy(moved).float()[crop].clamp(0, 1), reference[crop], (float(shift[0]), float(shift[1]))


def _deblurs(names: list[str], device: str) -> dict[str, Callable | str]:
    out: dict[str, Callable | str] = {}
    for name in names:
        if name in ("none", "physics", "blind"):
            out[name] = name
        else:
            out[name] = Restorer(resolve_weights(name), device=device).restore
    return out


def physics_deblur_for(record: dict, depth: torch.Tensor, fusion: str = "mean") -> PhysicsDeblur:
    """The physics deblur at the clip's true D/r0 and optics, with the mean depth modulation of Eq. 4 (after the
    sharpest fusion, the OTF of a weaker turbulence and the Laplacian prior: :meth:`PhysicsDeblur.for_fusion`)."""
    params = TurbulenceParams(**{k: v for k, v in record.get("params", {}).items() if k in _PARAM_KEYS})
    m = depth_modulation(depth[None], params.modulation, params.offset_s)
    dr0 = float(record["dr0"])
    return PhysicsDeblur.for_fusion(dr0, params.lambda_over_d_px, fusion, modulation=float(m.mean()))


_PARAM_KEYS = ("aperture_m", "wavelength_m", "path_length_m", "ifov_rad", "modulation", "offset_s")


def box_psnr(image: torch.Tensor, reference: torch.Tensor, box, offset: int = 0) -> float | None:
    """PSNR of ``image`` against ``reference`` (C, H, W) inside ``box`` [x0, y0, x1, y1] (end exclusive) of the frame,
    for images cropped by ``offset`` px on every side (the offset-removed ones); None when fewer than ``MIN_BOX_PX``
    pixels of the box are inside."""
    h, w = image.shape[-2:]
    x0, y0, x1, y1 = (int(v) - offset for v in box)
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    if (x1 - x0) * (y1 - y0) < MIN_BOX_PX or x1 <= x0 or y1 <= y0:
        return None
    return float(psnr(image[None, :, y0:y1, x0:x1], reference[None, :, y0:y1, x0:x1]))


def _clip_scores(item: dict, deblurs: dict[str, Callable], restorer, stride: int) -> dict[str, float]:
    """Means over one clip's frames: ``epe``, ``epe_zero`` (every frame) and ``"<row> psnr"``, ``"<row> ssim"``, their
    ``_aligned`` versions and ``"<row> cwssim"`` of each row (every ``stride``-th frame); with a truth per frame
    (field clips) each frame against its own, and ``"<row> box_psnr"``, ``box_psnr_aligned`` inside the objects'
    boxes."""
    frames, gt_all = item["turb"], item["gt"]
    boxes = item.get("boxes")
    observable = item["bwd_flow_px"] - item["bwd_flow_px"].mean(0, keepdim=True)
    temporal_mean = frames.mean(0)
    mean = KeyedMean(sync_on_compute=False)
    for o in restorer.restore(frames):
        flow = observable[o.index]
        mean.update({"epe": float(end_point_error(o.bwd_flow_px, flow)), "epe_zero": float(end_point_error(flow))})
        if o.index % stride:
            continue
        gt = gt_all[o.index] if gt_all.ndim == 4 else gt_all
        images = {"input": frames[o.index], "temporal mean": temporal_mean, "fused": o.fused}
        for name, fn in deblurs.items():
            if hasattr(fn, "observe"):  # as ClipRestorer does for its own deblur (the blind one reads the flow)
                fn.observe(o)
            # the restorer's deblur stage: tone guard, fallback kept (the live preset: its own)
            live = isinstance(restorer, LiveRestorer)
            images[f"fused + {name}"] = live_deblurred(fn, o.fused) if live else deblurred(fn, o)
        for row, img in images.items():
            img = img.clamp(0, 1)
            moved, ref, _ = remove_global_offset(img, gt)
            mean.update(
                {
                    f"{row} psnr": float(psnr(img[None], gt[None])),
                    f"{row} ssim": float(ssim(img[None], gt[None])),
                    f"{row} psnr_aligned": float(psnr(moved[None], ref[None])),
                    f"{row} ssim_aligned": float(ssim(moved[None], ref[None])),
                    f"{row} cwssim": cw_ssim(img, gt),
                }
            )
            if boxes is None:
                continue
            margin = (img.shape[-1] - moved.shape[-1]) // 2
            for box in boxes[o.index].tolist():
                if box[0] < 0:
                    continue
                plain, aligned = box_psnr(img, gt, box), box_psnr(moved, ref, box, margin)
                if plain is not None and aligned is not None:
                    mean.update({f"{row} box_psnr": plain, f"{row} box_psnr_aligned": aligned})
    return mean.compute()


def evaluate_clips(
    root: str | os.PathLike,
    out: str | os.PathLike,
    deblur: list[str] = ("physics",),
    temporal: int = MEASURED_TEMPORAL,
    preset: str = DEFAULT_PRESET,
    fusion: str = DEFAULT_FUSION,
    passes: int = 2,
    stride: int = 4,
    max_samples: int | None = None,
    device: str = "cpu",
    progress: bool = True,
    lookahead: int | None = None,
) -> dict:
    """Evaluate clip restoration on the sequence dataset at ``root``; writes OUT/results.json and results.md.

    Args:
        deblur: deblur options compared after fusion: "physics" (Wiener at the clip's true D/r0 and optics),
            "blind" (the default of ``restore --temporal``: restore.blur.BlindDeblur, estimated per clip), weights
            names/paths (a model on the fused frame); "none" is always the "fused" row.
        preset: a command line ``--preset`` (``clip.live.PRESETS``): "balanced" (the default's registration), "medium",
            "fine", or "fast": the live restorer (``clip.live``; its own mean fusion and luma deblur: ``fusion`` and
            ``passes`` unused).
        fusion: the restorer's fusion ("mean", "robust" or "fba").
        stride: image metrics on every ``stride``-th frame (the displacement error on every frame).
        lookahead: the restorer's (:class:`~d2turb.clip.ClipRestorer`): None for centred windows (a file's), L for
            output t waiting for input t + L at most (a stream's windows).
    """
    data = SequenceDataset(root)
    if not isinstance(stride, int) or stride < 1:
        raise D2TurbError(f"stride must be a positive integer, got {stride!r}")
    options = _deblurs([d for d in deblur if d != "none"], device)
    rows = list(ROWS) + [f"fused + {name}" for name in options]
    per_bin = KeyedMean(sync_on_compute=False)  # clip means, per bin
    samples = []
    n = len(data) if max_samples is None else min(len(data), max_samples)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n, desc="clips", unit="clip")
    for idx in range(n):
        item, record = data[idx], data.records[idx]
        deblurs = {}
        for name, fn in options.items():
            if fn == "physics":
                fn = physics_deblur_for(record, item["depth"], fusion)
            elif fn == "blind":
                fn = BlindDeblur(fusion=fusion)  # decides on this clip's first fused frame
            deblurs[name] = fn
        if dis_preset(preset) is None:  # the live preset: one pass, its mean, its deblur (clip.live)
            restorer = LiveRestorer(temporal)
        else:
            dis = dis_preset(preset)
            restorer = ClipRestorer(temporal=temporal, preset=dis, passes=passes, fusion=fusion, lookahead=lookahead)
        frame_means = _clip_scores(item, deblurs, restorer, stride)
        sample = {"id": item["id"], "bin": record["bin"], "dr0": float(record["dr0"])} | frame_means
        if isinstance(deblurs.get("blind"), BlindDeblur) and deblurs["blind"].record is not None:
            sample["blind"] = deblurs["blind"].record
        samples.append(sample)
        per_bin.update({k: v for k, v in sample.items() if isinstance(v, float)}, groups=record["bin"])
        if bar is not None:
            bar.update()
    if bar is not None:
        bar.close()
    table = {b: per_bin.compute(b) | {"clips": per_bin.count("epe", b)} for b in BINS if per_bin.count("epe", b)}
    results = {
        "dataset": str(root),
        "settings": {
            "temporal": temporal,
            "preset": preset,
            "fusion": fusion,
            "passes": passes,
            "stride": stride,
            "deblur": list(options),
        }
        | ({} if lookahead is None else {"lookahead": lookahead}),
        "rows": rows,
        "bins": table,
        "samples": samples,
    }
    out = Path(out)
    write_json(out / "results.json", results)
    write_text(out / "results.md", markdown(results))
    return results


def markdown(results: dict) -> str:
    """Per-bin table: PSNR / SSIM of each row, displacement end-point error against the observable flow and zero."""
    bins = list(results["bins"])
    lines = ["| | " + " | ".join(f"{b} PSNR | {b} SSIM" for b in bins) + " |", "|---|" + "---:|" * (2 * len(bins))]
    for row in results["rows"]:
        cells = [f"{results['bins'][b][row + ' psnr']:.2f} | {results['bins'][b][row + ' ssim']:.3f}" for b in bins]
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    if all(row + " psnr_aligned" in results["bins"][b] for b in bins for row in results["rows"]):
        lines.append("")
        lines.append(
            f"Global offset removed (each frame shifted onto the clean image, {OFFSET_MARGIN_PX} px border left out):"
        )
        lines.append("")
        lines.append("| | " + " | ".join(f"{b} PSNR | {b} SSIM" for b in bins) + " |")
        lines.append("|---|" + "---:|" * (2 * len(bins)))
        for row in results["rows"]:
            t = results["bins"]
            cells = [f"{t[b][row + ' psnr_aligned']:.2f} | {t[b][row + ' ssim_aligned']:.3f}" for b in bins]
            lines.append(f"| {row} | " + " | ".join(cells) + " |")
    if all(row + " box_psnr_aligned" in results["bins"][b] for b in bins for row in results["rows"]):
        t = results["bins"]
        lines += [
            "",
            "Inside the moving objects' boxes (PSNR; offset removed; gain over the input frame in brackets):",
            "",
        ]
        lines.append("| | " + " | ".join(f"{b} PSNR | {b} offset removed" for b in bins) + " |")
        lines.append("|---|" + "---:|" * (2 * len(bins)))
        for row in results["rows"]:
            cells = []
            for b in bins:
                plain, aligned = t[b][row + " box_psnr"], t[b][row + " box_psnr_aligned"]
                gain = aligned - t[b]["input box_psnr_aligned"]
                cells.append(f"{plain:.2f} | {aligned:.2f} ({gain:+.2f})")
            lines.append(f"| {row} | " + " | ".join(cells) + " |")
    if all(row + " cwssim" in results["bins"][b] for b in bins for row in results["rows"]):
        lines += ["", "CW-SSIM (Sampat et al. 2009; shift-tolerant, no offset removed):", ""]
        lines.append("| | " + " | ".join(bins) + " |")
        lines.append("|---|" + "---:|" * len(bins))
        for row in results["rows"]:
            lines.append(f"| {row} | " + " | ".join(f"{results['bins'][b][row + ' cwssim']:.4f}" for b in bins) + " |")
    lines.append("")
    lines.append("| | " + " | ".join(bins) + " |")
    lines.append("|---|" + "---:|" * len(bins))
    lines.append("| clips | " + " | ".join(str(results["bins"][b]["clips"]) for b in bins) + " |")
    lines.append(
        "| EPE vs observable flow (px) | " + " | ".join(f"{results['bins'][b]['epe']:.3f}" for b in bins) + " |"
    )
    lines.append("| EPE of zero (px) | " + " | ".join(f"{results['bins'][b]['epe_zero']:.3f}" for b in bins) + " |")
    return "\n".join(lines) + "\n"
