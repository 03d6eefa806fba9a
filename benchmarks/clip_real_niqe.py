"""NIQE of clip restoration on the real multi-frame clips (issue 23, acceptance 2; docs/clips.md 'Real clips').

    PYTHONPATH=src python3 benchmarks/clip_real_niqe.py [--data ../shared/data/real] [--clips NAME ...]
        [--fusion mean fba] [--deblur physics ...] [--temporal 32] [--frames 96] [--stride 6] [--dr0-cache FILE]
        [--controls] [--json FILE]

For each clip: D/r0 as ``d2turb restore --deblur auto`` finds it: measured by ``d2turb.clip.strength.measure_clip``
on its first 64 frames (default optics, 50 bootstrap resamples), or, for a clip the measurement refuses, estimated
from the registered displacement of those frames (``d2turb.clip.registration_dr0``; ``--refused none``: no deblur).
Then ``ClipRestorer(temporal, fusion=...)`` over the first ``--frames`` frames, and NIQE (``d2turb.eval.niqe``) of
every ``--stride``-th frame: the input frame, the fused frame, the fused frame after each deblur variant
(:func:`physics_variants`), and the same variant's filter on the single input frame (what single-frame ``restore``
does with that deblur). Only the sampled frames are fused (the restorer's other outputs are skipped; the sampled
ones are unchanged). Prints and writes one JSON object (means per clip and row).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import time
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import torch

from d2turb.clip import (
    ClipRestorer,
    PhysicsDeblur,
    default_balance,
    flow_variance_px2,
    registration_dr0,
)
from d2turb.clip.strength import measure_clip
from d2turb.errors import D2TurbError
from d2turb.eval.niqe import niqe
from d2turb.io import to_uint8
from d2turb.restore.clip_build import MEASURE_FRAMES
from d2turb.restore.clip_source import clip_frames
from d2turb.restore.single import Restorer

CLIPS = {
    "airport_heat_shimmer": "airport_heat_shimmer",
    **{f"clear_hot_air/test{i}": f"clear_hot_air/test{i}.mp4" for i in range(1, 6)},
}
ROOT = Path(__file__).resolve().parents[1]


RESIDUAL_TO_OBSERVED = 0.6  # validation clips: σ of the residual misregistration / σ of the registered flow


def physics_variants(name: str, dr0, flows: list, lambda_over_d_px: float = 2.0):
    """(deblur of a fused frame, deblur of a single frame, description) of a variant, or None (no D/r0).

    physics: the default (``PhysicsDeblur(dr0)``) on both; ``physics@M``: the same with M times its Wiener weight
    (the Laplacian prior's balance, ``default_balance(dr0)``) on both; jitter: the fused frame's OTF also carries
    the residual registration jitter, σ = RESIDUAL_TO_OBSERVED × the rms of the clip's registered flows (the single
    frame has none); ``model:NAME``: the restoration model NAME (a weights name or file) on both, as ``--deblur NAME``
    and single-frame ``restore --weights NAME`` do (no D/r0 needed)."""
    if name.startswith("model:"):
        restore = Restorer(name.split(":", 1)[1]).restore
        return restore, restore, name.split(":", 1)[1]
    if dr0 is None:
        return None
    desc = f"D/r0 {dr0:.3g}"
    if name == "physics":
        return PhysicsDeblur(dr0, lambda_over_d_px), PhysicsDeblur(dr0, lambda_over_d_px), desc
    if name.startswith("physics@"):
        balance = float(name.split("@", 1)[1]) * default_balance(dr0)
        deblur = PhysicsDeblur(dr0, lambda_over_d_px, balance=balance)
        return deblur, deblur, desc + f", balance {balance:.3g}"
    if name == "jitter":
        jit = RESIDUAL_TO_OBSERVED * float(np.mean([flow_variance_px2(f) for f in flows])) ** 0.5
        return (
            PhysicsDeblur(dr0, lambda_over_d_px, jitter_px=jit),
            PhysicsDeblur(dr0, lambda_over_d_px),
            desc + f", jitter {jit:.3g} px",
        )
    raise ValueError(f"unknown deblur variant {name!r}")


def _frames(path: Path, n: int) -> list:
    _, frames = clip_frames(path, SimpleNamespace(record=lambda exc: print(f"note: {exc}")))
    return list(itertools.islice(frames, n))


def _measure(path: Path, refused: str) -> dict:
    """D/r0 as ``d2turb restore --deblur auto`` finds it: measured, or (``refused`` = registration) estimated from
    the registered displacement of the first 64 frames when the measurement refuses the clip."""
    head = _frames(path, MEASURE_FRAMES)
    try:
        return {"dr0": float(measure_clip(head, {}, bootstrap=50)["dr0"]), "refused": None}
    except D2TurbError as exc:
        dr0 = registration_dr0(head) if refused == "registration" else None
        return {"dr0": dr0, "refused": str(exc), "source": f"{refused}"}


def _f32(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(a.astype(np.float32) / 255).permute(2, 0, 1)


# Controls: what NIQE makes of a light denoise of the input frame alone (no fusion, no deblur)
CONTROLS = {
    "input + Gaussian 0.5 px": lambda x: _f32(cv2.GaussianBlur(to_uint8(x), (0, 0), 0.5)),
    "input + NL-means h 3": lambda x: _f32(cv2.fastNlMeansDenoisingColored(to_uint8(x), None, 3, 3, 7, 21)),
}


def run_clip(
    path: Path,
    dr0,
    fusion: str,
    variants: list[str],
    temporal: int,
    frames: int,
    stride: int,
    controls: bool = False,
) -> dict:
    clip = _frames(path, frames)
    wanted = set(range(0, len(clip), stride))
    restorer = ClipRestorer(temporal=temporal, fusion=fusion)  # every frame fused (the seconds count them all)
    t0 = time.perf_counter()
    fused = {}
    flows = []
    for out in restorer.restore(clip):
        flows.append(out.bwd_flow_px)
        if out.index in wanted:
            fused[out.index] = out.fused
    seconds = time.perf_counter() - t0
    rows: dict[str, list[float]] = {"input": [], "fused": []}
    info = {}
    for i in sorted(wanted):
        rows["input"].append(float(niqe(clip[i])))
        rows["fused"].append(float(niqe(fused[i])))
    for name, control in CONTROLS.items() if controls else ():
        rows[name] = [float(niqe(control(clip[i]))) for i in sorted(wanted)]
    for name in variants:
        built = physics_variants(name, dr0, flows)
        if built is None:
            continue
        multi, single, desc = built
        info[name] = desc
        rows[f"{name}: restored"] = [float(niqe(multi(fused[i]))) for i in sorted(wanted)]
        rows[f"{name}: single-frame"] = [float(niqe(single(clip[i]))) for i in sorted(wanted)]
    return {
        "frames": len(clip),
        "size": list(clip[0].shape[-2:]),
        "sampled": sorted(wanted),
        "restore_s": round(seconds, 1),
        "deblur": info,
        "niqe": {k: round(float(np.mean(v)), 3) for k, v in rows.items()},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "real")
    ap.add_argument("--clips", nargs="+", default=list(CLIPS), choices=list(CLIPS))
    ap.add_argument("--fusion", nargs="+", default=["mean", "fba"])
    ap.add_argument("--deblur", nargs="+", default=["physics"])
    ap.add_argument("--temporal", type=int, default=32)
    ap.add_argument("--frames", type=int, default=96)
    ap.add_argument("--stride", type=int, default=6)
    ap.add_argument("--dr0-cache", type=Path, help="JSON of measured D/r0 per clip (read if present, else written)")
    ap.add_argument(
        "--refused", default="registration", choices=["none", "registration"], help="D/r0 when measure refuses"
    )
    ap.add_argument("--controls", action="store_true", help="also a light denoise of the input frame (CONTROLS)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    cache = json.loads(args.dr0_cache.read_text()) if args.dr0_cache and args.dr0_cache.exists() else {}
    result = {
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "machine": {"cpus": os.cpu_count(), "load": os.getloadavg(), "python": platform.python_version()},
        "clips": {},
    }
    for name in args.clips:
        path = args.data / CLIPS[name]
        if name not in cache or (cache[name]["dr0"] is None and args.refused != cache[name].get("source")):
            cache[name] = _measure(path, args.refused)
            if args.dr0_cache:
                args.dr0_cache.write_text(json.dumps(cache, indent=1))
        entry = {"measured": cache[name]}
        for fusion in args.fusion:
            entry[fusion] = run_clip(
                path, cache[name]["dr0"], fusion, args.deblur, args.temporal, args.frames, args.stride, args.controls
            )
            print(name, fusion, json.dumps(entry[fusion]["niqe"]), flush=True)
        result["clips"][name] = entry
    text = json.dumps(result, indent=1)
    if args.json:
        args.json.write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
