"""Real clips report (``d2turb evaluate --real-clips DIR``): each clip of a folder restored once with the defaults of
``d2turb restore CLIP --temporal N``, and per clip a contact sheet, the blind estimate used, the residual
frame-to-frame motion and NIQE / PIQE of the input, the default's fused frame before its deblur (the mean fusion:
``--deblur none --fusion mean``) and the default (docs/clips.md, "Real clips report").

A clip is a video file directly in DIR or in one of its sub-folders, or a sub-folder of at least
``MIN_CLIP_FRAMES`` image frames of one size (DIR itself too, when it holds such frames); anything else is listed
as not a clip, with the reason. One registration pass per clip: its :class:`~d2turb.clip.ClipFrame` gives both the
mean-fused frame (``fused``) and the default (``restored``).
"""

from __future__ import annotations

import itertools
import math
import os
import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from d2turb.clip.blind import BlindDeblur
from d2turb.clip.registration import DenseFlow, to_gray_u8, to_hwc
from d2turb.defaults import DEFAULT_FUSION, DEFAULT_REAL_CLIP_FRAMES, DEFAULT_TEMPORAL
from d2turb.errors import D2TurbError
from d2turb.eval.niqe import niqe
from d2turb.eval.piqe import piqe
from d2turb.io import list_images, to_uint8, write_image, write_json, write_text
from d2turb.restore.files import check_frame_sizes, clip_frames, clip_restorer
from d2turb.video import VIDEO_SUFFIXES, is_video, video_size

MIN_CLIP_FRAMES = 4  # a folder with fewer frames is not a clip (e.g. three frames 20 apart)
SCORE_STRIDE = 8  # NIQE / PIQE on every SCORE_STRIDE-th frame, from SCORE_STRIDE // 2
CROP_PX = 160  # side of the zoomed crop (at most half the frame's shorter side)
ZOOM = 3  # nearest-neighbour zoom of the crop
PANEL_PX = 480  # width of each column of the sheet
MOTION_PRESET = "fast"  # DIS preset of the residual-motion measurement (the restoration's default registration)
COLUMNS = ("input", "none", "default")
LABELS = {"input": "input", "none": "mean fusion (no deblur)", "default": "default (blind deblur)"}


# ---- which entries are clips ---------------------------------------------------------------------------------------
def _visible(entries) -> list[Path]:
    return sorted(p for p in entries if not p.name.startswith("."))


def _frames_clip(folder: Path) -> str | None:
    """None when ``folder``'s images make a clip, else the reason they do not."""
    files = list_images(folder)
    if len(files) < MIN_CLIP_FRAMES:
        return f"{len(files)} image(s): a clip needs at least {MIN_CLIP_FRAMES} frames"
    try:
        check_frame_sizes(folder, files)
    except D2TurbError as exc:
        return f"not one clip ({str(exc).split(': ', 1)[-1]})"
    return None


def find_clips(root: str | os.PathLike) -> tuple[dict[str, Path], list[dict]]:
    """The clips of ``root``: ({name: video file or folder of frames}, [{"path", "reason"} of what is not a clip]).

    Names are paths relative to ``root`` (a video without its suffix: ``clear_hot_air/test1``; ``root`` itself is
    ``.``). Raises ``D2TurbError`` when ``root`` is not a folder or holds no clip.
    """
    root = Path(root)
    if not root.is_dir():
        raise D2TurbError(f"{root}: not a directory (--real-clips takes a folder of clips)")
    clips: dict[str, Path] = {}
    not_clips: list[dict] = []
    entries = _visible(root.iterdir())
    if list_images(root):  # root's own frames
        reason = _frames_clip(root)
        if reason is None:
            clips["."] = root
        else:
            not_clips.append({"path": ".", "reason": reason})
    for entry in entries:
        rel = entry.relative_to(root).as_posix()
        if entry.is_file() and entry.suffix.lower() in VIDEO_SUFFIXES:
            clips[str(Path(rel).with_suffix(""))] = entry
        elif entry.is_dir():
            videos = [p for p in _visible(entry.iterdir()) if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES]
            for v in videos:
                clips[v.relative_to(root).with_suffix("").as_posix()] = v
            images = list_images(entry)
            if videos and images:
                not_clips.append({"path": rel, "reason": f"{len(images)} image(s) beside its videos (not a clip)"})
            elif not videos:
                reason = _frames_clip(entry)
                if reason is None:
                    clips[rel] = entry
                else:
                    not_clips.append({"path": rel, "reason": reason})
    if not clips:
        why = "; ".join(f"{n['path']}: {n['reason']}" for n in not_clips) or "it is empty"
        raise D2TurbError(f"{root}: no clips (a video file or a folder of {MIN_CLIP_FRAMES}+ frames); {why}")
    return clips, not_clips


def _expected_frames(src: Path, max_frames: int) -> int | None:
    """Frames the run will read (bounded by ``max_frames``), None when a video's container does not say."""
    if is_video(src):
        try:
            stored = video_size(src)[0]
        except D2TurbError:
            return None
        return min(stored, max_frames) if stored else None
    return min(len(list_images(src)), max_frames)


# ---- measurements --------------------------------------------------------------------------------------------------
class MotionMeter:
    """Residual frame-to-frame motion of a stream of frames: per consecutive pair the mean |DIS flow| (px) of the
    later frame onto the earlier (:class:`~d2turb.clip.registration.DenseFlow`); ``median`` over the pairs."""

    def __init__(self, preset: str = MOTION_PRESET):
        self.flow = DenseFlow(preset)
        self.previous: np.ndarray | None = None
        self.values: list[float] = []

    def add(self, frame) -> None:
        """Add the next frame ((3,H,W) tensor or (H,W,3) array in [0,1])."""
        grey = to_gray_u8(to_hwc(frame))
        if self.previous is not None:
            f = self.flow(self.previous, grey)
            self.values.append(float(np.sqrt((f**2).sum(axis=2)).mean()))
        self.previous = grey

    @property
    def median(self) -> float:
        return float(np.median(self.values)) if self.values else math.nan


def textured_window(image: torch.Tensor, size: int) -> tuple[int, int]:
    """(y, x) of the ``size``² window of ``image`` with the most gradient energy (sum of |∇ luma|²), on an 8 px
    grid: where the crops of the sheet show detail, halos and ringing."""
    g = to_gray_u8(to_hwc(image)).astype(np.float32) / 255
    gx, gy = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    energy = cv2.integral((gx * gx + gy * gy).astype(np.float64))
    h, w = g.shape
    ys, xs = np.arange(0, h - size + 1, 8), np.arange(0, w - size + 1, 8)
    sums = (
        energy[ys[:, None] + size, xs[None] + size]
        - energy[ys[:, None], xs[None] + size]
        - energy[ys[:, None] + size, xs[None]]
        + energy[ys[:, None], xs[None]]
    )
    iy, ix = np.unravel_index(int(np.argmax(sums)), sums.shape)
    return int(ys[iy]), int(xs[ix])


def crop_side(height: int, width: int) -> int:
    """Side of the zoomed crop: ``CROP_PX``, at most half the frame's shorter side."""
    return max(8, min(CROP_PX, min(height, width) // 2))


def _font(size: int):
    """DejaVu Sans from matplotlib (a dependency; it has λ and σ), else Pillow's default font."""
    try:
        import matplotlib

        return ImageFont.truetype(str(Path(matplotlib.get_data_path()) / "fonts" / "ttf" / "DejaVuSans.ttf"), size)
    except (ImportError, OSError):
        return ImageFont.load_default(size=size)


def contact_sheet(images: dict[str, torch.Tensor], window: tuple[int, int, int], title: str = "") -> np.ndarray:
    """Columns input | mean fusion | default: the whole frame (scaled to ``PANEL_PX`` wide, the crop outlined)
    above its crop ``window`` = (y, x, side) zoomed ×``ZOOM`` or more (nearest neighbour), labelled → (H, W, 3)
    uint8."""
    y, x, side = window
    zoom = max(ZOOM, PANEL_PX // side)  # small frames: the crop fills the column
    panel = max(PANEL_PX, side * zoom)
    font = _font(18)
    band, gap = 30, 8
    columns = []
    for key in COLUMNS:
        frame = Image.fromarray(to_uint8(images[key].clamp(0, 1)))
        scale = panel / frame.width
        whole = frame.resize((panel, round(frame.height * scale)), Image.Resampling.LANCZOS)
        draw = ImageDraw.Draw(whole)
        box = [x * scale, y * scale, (x + side) * scale - 1, (y + side) * scale - 1]
        draw.rectangle(box, outline=(255, 0, 0), width=2)
        crop = frame.crop((x, y, x + side, y + side)).resize((side * zoom, side * zoom), Image.Resampling.NEAREST)
        columns.append((LABELS[key], whole, crop))
    whole_h = max(c[1].height for c in columns)
    crop_h = max(c[2].height for c in columns)
    top = band + (band if title else 0)
    sheet = Image.new("RGB", (3 * panel + 2 * gap, top + whole_h + gap + crop_h), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    if title:
        draw.text((4, 4), title, fill=(0, 0, 0), font=font)
    for k, (label, whole, crop) in enumerate(columns):
        left = k * (panel + gap)
        draw.text((left + 4, top - band + 4), label, fill=(0, 0, 0), font=font)
        sheet.paste(whole, (left, top))
        sheet.paste(crop, (left + (panel - crop.width) // 2, top + whole_h + gap))
    return np.asarray(sheet)


def _scores(image: torch.Tensor, notes: set) -> dict[str, float]:
    """NIQE and PIQE of an image; a metric that cannot score it (too small, flat) is NaN, its reason in ``notes``."""
    image = image.clamp(0, 1)
    values = {}
    for name, metric in (("niqe", niqe), ("piqe", piqe)):
        try:
            values[name] = float(metric(image))
        except D2TurbError as exc:
            values[name] = math.nan
            notes.add(str(exc))
    return values


# ---- one clip --------------------------------------------------------------------------------------------------
def evaluate_clip(
    src: Path,
    temporal: int,
    max_frames: int = DEFAULT_REAL_CLIP_FRAMES,
    stride: int = SCORE_STRIDE,
    progress: bool = False,
) -> tuple[dict, np.ndarray]:
    """Restore one clip (its first ``max_frames`` frames) once with restore's defaults and measure it.

    Args:
        src: a video file or a folder of frames.
        temporal: the restoration's window; must be shorter than the clip.
        stride: NIQE / PIQE of every ``stride``-th frame (from ``stride // 2``).

    Returns:
        (the clip's entry of results.json, its contact sheet as (H, W, 3) uint8).
    """
    expected = _expected_frames(src, max_frames)
    if expected is not None and expected <= temporal:
        raise D2TurbError(f"{src}: {expected} frame(s); --temporal {temporal} must be shorter than the clip")
    restorer, _, _ = clip_restorer(src, temporal, fusion=DEFAULT_FUSION)
    errors: list[str] = []
    score_notes: set[str] = set()
    _, frames = clip_frames(src, SimpleNamespace(record=lambda exc: errors.append(str(exc))))  # bad frames: skipped
    pick = (expected or max_frames) // 2  # the sheet's frame (else the last scored one, if the clip is shorter)
    inputs: dict[int, torch.Tensor] = {}  # kept until restored: only the scored frames and the sheet's
    motion_in, motion_out = MotionMeter(), MotionMeter()

    def read():
        for i, frame in enumerate(itertools.islice(frames, max_frames)):
            motion_in.add(frame)
            if i % stride == stride // 2 or i == pick:
                inputs[i] = frame
            yield frame

    started = time.perf_counter()
    sums: dict[str, dict[str, float]] = {c: {"niqe": 0.0, "piqe": 0.0} for c in COLUMNS}
    scored, sheet_images, count = 0, None, 0
    stream = restorer.restore(read())
    if progress:
        from tqdm import tqdm

        stream = tqdm(stream, desc=src.name, unit="frame", total=expected)
    for out in stream:
        count += 1
        motion_out.add(out.restored)
        before = inputs.pop(out.index, None)
        if before is None:
            continue
        images = {"input": before, "none": out.fused, "default": out.restored}
        if out.index == pick or (sheet_images is None and out.index % stride == stride // 2):
            sheet_images = images
        if out.index % stride == stride // 2:
            for column, image in images.items():
                for metric, value in _scores(image, score_notes).items():
                    sums[column][metric] += value
            scored += 1
    seconds = time.perf_counter() - started
    if count <= temporal:
        raise D2TurbError(f"{src}: {count} frame(s) read; --temporal {temporal} must be shorter than the clip")
    if sheet_images is None:
        raise D2TurbError(f"{src}: {count} frame(s) read: too few for the report (need {stride // 2 + 1})")
    if not scored:  # the sheet's frame only
        for column, image in sheet_images.items():
            sums[column] = _scores(image, score_notes)
        scored = 1
    deblur = restorer.deblur
    side = crop_side(*sheet_images["input"].shape[-2:])
    y, x = textured_window(sheet_images["input"], side)
    entry = {
        "source": str(src),
        "frames": count,
        "size": list(sheet_images["input"].shape[-2:][::-1]),
        "temporal": temporal,
        "scored_frames": scored,
        "niqe": {c: sums[c]["niqe"] / scored for c in COLUMNS},
        "piqe": {c: sums[c]["piqe"] / scored for c in COLUMNS},
        "motion_px": {"input": motion_in.median, "default": motion_out.median},
        "deblur": deblur.record if isinstance(deblur, BlindDeblur) else None,
        "deblur_description": deblur.describe() if isinstance(deblur, BlindDeblur) else "none",
        "sheet_frame": pick if pick < count else stride // 2,
        "crop": {"y": y, "x": x, "side": side},
        "seconds": seconds,
        "frame_errors": errors,
        "score_notes": sorted(score_notes),
    }
    title = f"{src.name}: frame {entry['sheet_frame']}, {entry['deblur_description']}"
    return entry, contact_sheet(sheet_images, (y, x, side), title)


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
            "motion": f"median over consecutive frame pairs of the mean |DIS flow| (preset {MOTION_PRESET}), px",
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


def _estimate_cell(entry: dict) -> str:
    record = entry.get("deblur") or {}
    est = record.get("estimate")
    if not est:
        return "–"
    used = record.get("sigma_px", 0.0)
    text = f"σ {est['sigma_px']:.2f} px ({'confident' if est['confident'] else 'not confident'}); used {used:.2f}"
    if "learned" in record:
        b = record["learned"]
        text = (
            f"learned D/r0 {b['dr0']:.2f}, λ/(D·ifov) {b['lambda_over_d_px']:.2f} px, M {b['modulation']:.2f}; edges "
            + text
        )
    if "lambda_over_d_px" in record:
        text += f", λ/(D·ifov) {record['lambda_over_d_px']:.2f} px"
    return text


def markdown(results: dict) -> str:
    """The report's table: per clip NIQE / PIQE of input, mean fusion and default, residual motion, estimate."""
    s = results["settings"]
    lines = [
        f"# Real clips report: `{results['data']}`",
        "",
        f"Window {s['temporal']}, first {s['max_frames']} frames per clip; NIQE / PIQE (lower = more natural "
        f"statistics, no ground truth) mean over every {s['score_stride']}th frame; motion: {s['motion']}.",
        "",
        "| clip | frames | NIQE input / mean fusion / default | PIQE input / mean fusion / default "
        "| motion input → default (px) "
        "| blind estimate | deblur | note |",
        "|---|---:|---|---|---|---|---|---|",
    ]
    for name, e in results["clips"].items():
        niqe_cell = " / ".join(f"{e['niqe'][c]:.2f}" for c in COLUMNS)
        piqe_cell = " / ".join(f"{e['piqe'][c]:.1f}" for c in COLUMNS)
        motion = f"{e['motion_px']['input']:.3f} → {e['motion_px']['default']:.3f}"
        note = (e.get("deblur") or {}).get("note", "")
        lines.append(
            f"| {name} | {e['frames']} | {niqe_cell} | {piqe_cell} | {motion} | {_estimate_cell(e)} "
            f"| {e['deblur_description']} | {note} |"
        )
    if results["skipped"]:
        lines += ["", "## Skipped", ""] + [f"- `{s['clip']}`: {s['error']}" for s in results["skipped"]]
    if results["not_clips"]:
        lines += ["", "## Not clips", ""] + [f"- `{n['path']}`: {n['reason']}" for n in results["not_clips"]]
    return "\n".join(lines) + "\n"
