"""Real clips report (``d2turb evaluate --real-clips DIR``): each clip of a folder restored with the defaults of
``d2turb restore CLIP --temporal N`` and with ``--deblur none``; per clip a contact sheet, the blind estimate used,
the residual frame-to-frame motion, NIQE / PIQE, and what a person sees (:mod:`d2turb.eval.artifacts`: crushed
shadows and clipped highlights, the codec's block grid, noise in flat regions, edge sharpness, ghosts on the frames
where the camera shook most) of the input, the default's fused frame before its deblur (the mean fusion:
``--deblur none --fusion mean``), ``--deblur none`` (the sharpest fusion) and the default (docs/clips.md, "Real
clips report").

A clip is a video file directly in DIR or in one of its sub-folders, or a sub-folder of at least
``MIN_CLIP_FRAMES`` image frames of one size (DIR itself too, when it holds such frames); anything else is listed
as not a clip, with the reason. Per clip: one pass that measures the camera's shake (each frame's global shift from
the middle frame), the default's restoration (its :class:`~d2turb.clip.ClipFrame` gives both the mean-fused frame,
``fused``, and the default, ``restored``) and ``--deblur none``'s.

This module runs the restorations and writes the report; its pieces: :mod:`~d2turb.eval.real_clip_folders` (which
entries are clips), :mod:`~d2turb.eval.real_clip_measures` (motion, shake, what a person sees, NIQE / PIQE, the
checks), :mod:`~d2turb.eval.real_clip_sheet` (the contact sheet), :mod:`~d2turb.eval.real_clip_markdown`
(results.md).
"""

from __future__ import annotations

import itertools
import os
import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

from d2turb.clip.blind import BlindDeblur
from d2turb.defaults import DEFAULT_FUSION, DEFAULT_REAL_CLIP_FRAMES, DEFAULT_TEMPORAL, FUSION_WITHOUT_DEBLUR
from d2turb.errors import D2TurbError
from d2turb.eval import artifacts
from d2turb.eval.real_clip_folders import MIN_CLIP_FRAMES, expected_frames, find_clips
from d2turb.eval.real_clip_markdown import markdown
from d2turb.eval.real_clip_measures import (
    COLUMNS,
    METHODS,
    MOTION_PRESET,
    SHAKE_FRAMES,
    MotionMeter,
    camera_shifts,
    checks,
    finite_mean,
    frame_measures,
    niqe_piqe,
    shake_frames,
    textured_window,
    worst_windows,
)
from d2turb.eval.real_clip_sheet import contact_sheet, crop_side
from d2turb.io import to_uint8, write_image, write_json, write_text
from d2turb.restore.clip_build import clip_restorer
from d2turb.restore.clip_source import clip_frames

__all__ = ["MIN_CLIP_FRAMES", "evaluate_clip", "evaluate_real_clips", "find_clips", "markdown", "textured_window"]

SCORE_STRIDE = 8  # NIQE / PIQE and the artifact measures on every SCORE_STRIDE-th frame, from SCORE_STRIDE // 2


# ---- one clip ------------------------------------------------------------------------------------------------------
class _Run:
    """One restoration of a clip: its outputs of the ``wanted`` frames with their input frames, and the residual
    motion of its input and output."""

    def __init__(self, restorer, src: Path, max_frames: int, wanted: set[int], errors=None, input_motion=True):
        self.restorer, self.src, self.max_frames, self.wanted = restorer, src, max_frames, wanted
        self.errors = [] if errors is None else errors
        self.motion_in, self.motion_out = (MotionMeter() if input_motion else None), MotionMeter()
        self.count = 0

    def outputs(self, progress: bool = False, desc: str = "", total: int | None = None):
        """Yields (index, input frame, ClipFrame) of the wanted frames, as the restoration gives them."""
        _, frames = clip_frames(self.src, SimpleNamespace(record=lambda exc: self.errors.append(str(exc))))
        inputs: dict[int, torch.Tensor] = {}  # kept until restored: only the wanted frames

        def read():
            for i, frame in enumerate(itertools.islice(frames, self.max_frames)):
                if self.motion_in is not None:
                    self.motion_in.add(frame)
                if i in self.wanted:
                    inputs[i] = frame
                yield frame

        stream = self.restorer.restore(read())
        if progress:
            from tqdm import tqdm

            stream = tqdm(stream, desc=desc, unit="frame", total=total)
        for out in stream:
            self.count += 1
            self.motion_out.add(out.restored)
            before = inputs.pop(out.index, None)
            if before is not None:
                yield out.index, before, out


def evaluate_clip(
    src: Path,
    temporal: int,
    max_frames: int = DEFAULT_REAL_CLIP_FRAMES,
    stride: int = SCORE_STRIDE,
    progress: bool = False,
) -> tuple[dict, np.ndarray]:
    """Restore one clip (its first ``max_frames`` frames) with restore's defaults and with ``--deblur none``, and
    measure it.

    Args:
        src: a video file or a folder of frames.
        temporal: the restoration's window; must be shorter than the clip.
        stride: NIQE / PIQE and the artifact measures of every ``stride``-th frame (from ``stride // 2``).

    Returns:
        (the clip's entry of results.json, its contact sheet as (H, W, 3) uint8).
    """
    expected = expected_frames(src, max_frames)
    if expected is not None and expected <= temporal:
        raise D2TurbError(f"{src}: {expected} frame(s); --temporal {temporal} must be shorter than the clip")
    restorer, _, _ = clip_restorer(src, temporal, fusion=DEFAULT_FUSION)
    started = time.perf_counter()
    shifts = camera_shifts(src, max_frames)
    n = len(shifts)
    if n <= temporal:
        raise D2TurbError(f"{src}: {n} frame(s) read; --temporal {temporal} must be shorter than the clip")
    if n <= stride // 2:
        raise D2TurbError(f"{src}: {n} frame(s) read: too few for the report (need {stride // 2 + 1})")
    shaken, calm = shake_frames(shifts)
    pick = n // 2  # the sheet's frame: the middle one, the shake's reference
    scored = [i for i in range(n) if i % stride == stride // 2]
    wanted = set(scored) | set(shaken) | set(calm) | {pick}
    most = max(shaken, key=lambda i: shifts[i])
    errors: list[str] = []
    score_notes: set[str] = set()
    per_frame: dict[str, list[dict]] = {c: [] for c in COLUMNS}
    scores: dict[str, list[dict]] = {c: [] for c in COLUMNS}
    ghosts: dict[str, dict[int, float]] = {m: {} for m in METHODS}
    sheet: dict[str, np.ndarray] = {}
    shaken_sheet: dict[str, np.ndarray] = {}

    def measure(index: int, reference: torch.Tensor, images: dict[str, torch.Tensor]) -> None:
        for column, image in images.items():
            image = image.clamp(0, 1)
            if index in scored:
                per_frame[column].append(frame_measures(image, reference))
                scores[column].append(niqe_piqe(image, score_notes))
            if column != "input" and (index in shaken or index in calm):
                ghosts[column][index] = artifacts.ghost_share(image, reference)
            if index == pick:
                sheet[column] = to_uint8(image)
            if index == most:
                shaken_sheet[column] = to_uint8(image)

    default = _Run(restorer, src, max_frames, wanted, errors)
    for index, before, out in default.outputs(progress, f"{src.name} default", n):
        reference = before.clamp(0, 1)
        measure(index, reference, {"input": reference, "mean": out.fused, "default": out.restored})
    if default.count <= temporal:
        raise D2TurbError(f"{src}: {default.count} frame(s) read; --temporal {temporal} must be shorter than the clip")
    none_restorer, _, _ = clip_restorer(src, temporal, deblur="none")
    plain = _Run(none_restorer, src, max_frames, wanted, input_motion=False)
    for index, before, out in plain.outputs(progress, f"{src.name} --deblur none", n):
        measure(index, before.clamp(0, 1), {"none": out.restored})
    seconds = time.perf_counter() - started

    measures = {c: {k: finite_mean([f[k] for f in per_frame[c]]) for k in per_frame["input"][0]} for c in COLUMNS}
    ghost = {}
    for m in METHODS:
        on_shaken = finite_mean([ghosts[m][i] for i in shaken if i in ghosts[m]])
        on_calm = finite_mean([ghosts[m][i] for i in calm if i in ghosts[m]])
        ghost[m] = {"shaken": on_shaken, "calm": on_calm, "excess": on_shaken - on_calm}
    side = crop_side(*sheet["input"].shape[:2])
    windows = worst_windows(sheet, None if most == pick else shaken_sheet, side)
    deblur = restorer.deblur
    entry = {
        "source": str(src),
        "frames": default.count,
        "size": list(sheet["input"].shape[:2][::-1]),
        "temporal": temporal,
        "scored_frames": len(scored),
        "niqe": {c: finite_mean([s["niqe"] for s in scores[c]]) for c in COLUMNS},
        "piqe": {c: finite_mean([s["piqe"] for s in scores[c]]) for c in COLUMNS},
        "measures": measures,
        "ghost": ghost,
        "checks": checks(measures, {m: ghost[m]["excess"] for m in METHODS}),
        "shake": {
            "shift_px": [round(v, 2) for v in shifts],
            "max_px": max(shifts),
            "shaken_frames": shaken,
            "calm_frames": calm,
        },
        "motion_px": {
            "input": default.motion_in.median,
            "none": plain.motion_out.median,
            "default": default.motion_out.median,
        },
        "deblur": deblur.record if isinstance(deblur, BlindDeblur) else None,
        "deblur_description": deblur.describe() if isinstance(deblur, BlindDeblur) else "none",
        "sheet_frame": pick,
        "ghost_frame": most,
        "crops": {k: {"y": y, "x": x, "side": side} for k, (y, x) in windows.items()},
        "seconds": seconds,
        "frame_errors": errors,
        "score_notes": sorted(score_notes),
    }
    title = f"{src.name}: frame {pick}, {entry['deblur_description']}"
    shaken_label = f"ghost check: frame {most}, {shifts[most]:.1f} px from frame {pick}'s pose"
    image = contact_sheet(sheet, windows, side, title, None if most == pick else shaken_sheet, shaken_label)
    return entry, image


# ---- the report ----------------------------------------------------------------------------------------------------
def evaluate_real_clips(
    root: str | os.PathLike,
    out: str | os.PathLike,
    temporal: int | None = None,
    max_frames: int = DEFAULT_REAL_CLIP_FRAMES,
    stride: int = SCORE_STRIDE,
    fail_fast: bool = False,
    on_skip: Callable[[str], None] | None = None,
    progress: bool = True,
) -> dict:
    """Report on every clip of ``root``: writes OUT/sheets/<clip>.png, OUT/results.json and OUT/results.md.

    Args:
        temporal: window of the restoration (default: ``DEFAULT_TEMPORAL``, the clip pipeline's).
        max_frames: frames read per clip (from its start).
        fail_fast: raise a clip's error instead of reporting it (``on_skip(message)``) and going on.

    Returns:
        The dict written to results.json: ``clips`` {name: entry of :func:`evaluate_clip`}, ``skipped``
        [{"clip", "error"}], ``not_clips`` [{"path", "reason"}] and the ``settings``.
    """
    temporal = DEFAULT_TEMPORAL if temporal is None else temporal
    if not isinstance(temporal, int) or temporal < 2:
        raise D2TurbError(f"--temporal must be an integer >= 2, got {temporal!r}")
    if not isinstance(stride, int) or stride < 1:
        raise D2TurbError(f"stride must be a positive integer, got {stride!r}")
    if not isinstance(max_frames, int) or max_frames <= temporal:
        raise D2TurbError(f"--max-frames must be larger than --temporal ({temporal}), got {max_frames!r}")
    clips, not_clips = find_clips(root)
    out = Path(out)
    results: dict = {
        "mode": "real-clips",
        "data": str(root),
        "settings": {
            "temporal": temporal,
            "max_frames": max_frames,
            "score_stride": stride,
            "restore": "d2turb restore CLIP --temporal N defaults (clip_restorer: passes 2, preset fast, "
            f"fusion {DEFAULT_FUSION}, deblur auto = blind)",
            "none": f"d2turb restore CLIP --temporal N --deblur none (fusion {FUSION_WITHOUT_DEBLUR})",
            "motion": f"median over consecutive frame pairs of the mean |DIS flow| (preset {MOTION_PRESET}), px",
            "measures": f"d2turb.eval.artifacts on the luma, mean over the scored frames: near-black ≤ "
            f"{artifacts.NEAR_BLACK_U8}/255 and near-white ≥ {artifacts.NEAR_WHITE_U8}/255 shares (%); block grid B/A "
            f"(Wang, Sheikh & Bovik 2002, {artifacts.BLOCK_PX}-px grid); flat-region noise σ (Immerkær 1996, the "
            f"input's flattest {artifacts.NOISE_SHARE:.0%} of {artifacts.NOISE_BLOCK_PX}² blocks, grey levels); "
            "sharpness: peak gradient at the input's strongest 2 % of pixels (grey levels / px)",
            "ghost": f"share of the output's edge strength absent from its input frame (artifacts.ghost_share), mean "
            f"over the {SHAKE_FRAMES} frames farthest from the middle frame's pose minus over the {SHAKE_FRAMES} "
            f"nearest; a ghost above {artifacts.GHOST_EXCESS_MAX}",
        },
        "clips": {},
        "skipped": [],
        "not_clips": not_clips,
    }
    for name, src in clips.items():
        try:
            entry, sheet = evaluate_clip(src, temporal, max_frames, stride, progress)
        except D2TurbError as exc:
            if fail_fast or len(clips) == 1:
                raise
            results["skipped"].append({"clip": name, "error": str(exc)})
            if on_skip is not None:
                on_skip(str(exc))
            continue
        sheet_name = "root" if name == "." else name
        entry["sheet"] = f"sheets/{sheet_name}.png"
        write_image(out / entry["sheet"], sheet)
        results["clips"][name] = entry
    write_json(out / "results.json", results)
    write_text(out / "results.md", markdown(results))
    return results
