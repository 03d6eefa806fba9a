"""Clip restoration on a sequence dataset (``make-dataset --frames N``), per strength bin: PSNR/SSIM of the input
frame, the plain temporal mean, the registered fusion and the fusion after each deblur option; end-point error of
the estimated displacement against the observable flow (the simulator's flow minus its temporal mean: a clip
cannot see its own mean tilt) and against zero. docs/clips.md."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import torch

from d2turb.data.sequence import SequenceDataset
from d2turb.defaults import DEFAULT_FUSION
from d2turb.errors import D2TurbError
from d2turb.eval.metrics import KeyedMean, end_point_error, psnr, ssim
from d2turb.io import write_json, write_text
from d2turb.models.hub import resolve_weights
from d2turb.restore.clip import ClipRestorer, PhysicsDeblur, deblur_dr0, default_balance
from d2turb.restore.single import Restorer
from d2turb.sim import TurbulenceParams, depth_modulation
from d2turb.sim.params import BINS

ROWS = ("input", "temporal mean", "fused")


def _deblurs(names: list[str], device: str) -> dict[str, Callable | str]:
    out: dict[str, Callable | str] = {}
    for name in names:
        if name in ("none", "physics"):
            out[name] = name
        else:
            out[name] = Restorer(resolve_weights(name), device=device).restore
    return out


def physics_deblur_for(record: dict, depth: torch.Tensor, fusion: str = "mean") -> PhysicsDeblur:
    """The physics deblur at the clip's true D/r0 and optics, with the mean depth modulation of Eq. 4 (after the
    sharpest fusion, the OTF of a weaker turbulence: :func:`~d2turb.restore.clip.deblur_dr0`)."""
    params = TurbulenceParams(**{k: v for k, v in record.get("params", {}).items() if k in _PARAM_KEYS})
    m = depth_modulation(depth[None], params.modulation, params.offset_s)
    dr0 = float(record["dr0"])
    return PhysicsDeblur(
        deblur_dr0(dr0, fusion), params.lambda_over_d_px, balance=default_balance(dr0), modulation=float(m.mean())
    )


_PARAM_KEYS = ("aperture_m", "wavelength_m", "path_length_m", "ifov_rad", "modulation", "offset_s")


def _clip_scores(item: dict, deblurs: dict[str, Callable], restorer: ClipRestorer, stride: int) -> dict[str, float]:
    """Means over one clip's frames: ``epe``, ``epe_zero`` (every frame) and ``"<row> psnr"``, ``"<row> ssim"`` of
    each row (every ``stride``-th frame)."""
    frames, gt = item["turb"], item["gt"]
    observable = item["bwd_flow_px"] - item["bwd_flow_px"].mean(0, keepdim=True)
    temporal_mean = frames.mean(0)
    mean = KeyedMean(sync_on_compute=False)
    for o in restorer.restore(frames):
        flow = observable[o.index]
        mean.update({"epe": float(end_point_error(o.bwd_flow_px, flow)), "epe_zero": float(end_point_error(flow))})
        if o.index % stride:
            continue
        images = {"input": frames[o.index], "temporal mean": temporal_mean, "fused": o.fused}
        for name, fn in deblurs.items():
            images[f"fused + {name}"] = fn(o.fused)
        for row, img in images.items():
            img = img.clamp(0, 1)[None]
            mean.update({f"{row} psnr": float(psnr(img, gt[None])), f"{row} ssim": float(ssim(img, gt[None]))})
    return mean.compute()


def evaluate_clips(
    root: str | os.PathLike,
    out: str | os.PathLike,
    deblur: list[str] = ("physics",),
    temporal: int = 32,
    preset: str = "fast",
    fusion: str = DEFAULT_FUSION,
    passes: int = 2,
    stride: int = 4,
    max_samples: int | None = None,
    device: str = "cpu",
    progress: bool = True,
) -> dict:
    """Evaluate clip restoration on the sequence dataset at ``root``; writes OUT/results.json and results.md.

    Args:
        deblur: deblur options compared after fusion: "physics" (Wiener at the clip's true D/r0 and optics),
            weights names/paths (a model on the fused frame); "none" is always the "fused" row.
        fusion: the restorer's fusion ("mean", "robust" or "fba").
        stride: image metrics on every ``stride``-th frame (the displacement error on every frame).
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
        deblurs = {
            name: (physics_deblur_for(record, item["depth"], fusion) if fn == "physics" else fn)
            for name, fn in options.items()
        }
        restorer = ClipRestorer(temporal=temporal, preset=preset, passes=passes, fusion=fusion)
        frame_means = _clip_scores(item, deblurs, restorer, stride)
        sample = {"id": item["id"], "bin": record["bin"], "dr0": float(record["dr0"])} | frame_means
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
        },
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
    lines.append("")
    lines.append("| | " + " | ".join(bins) + " |")
    lines.append("|---|" + "---:|" * len(bins))
    lines.append("| clips | " + " | ".join(str(results["bins"][b]["clips"]) for b in bins) + " |")
    lines.append(
        "| EPE vs observable flow (px) | " + " | ".join(f"{results['bins'][b]['epe']:.3f}" for b in bins) + " |"
    )
    lines.append("| EPE of zero (px) | " + " | ".join(f"{results['bins'][b]['epe_zero']:.3f}" for b in bins) + " |")
    return "\n".join(lines) + "\n"
