"""What each tab's button does, in plain Python (no gradio): check the page's values, put the inputs into a fresh
run folder, run the job's command there (:mod:`d2turb.app.jobs`: one argument list per job, the one shown), then
read its files back for the pictures and numbers the page shows, and zip the run for download."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from d2turb.app.forms import (
    IMAGE_SOURCES,
    Limits,
    SimSettings,
    check_pixels,
    known,
    safe_stem,
    sample_image,
    sim_values,
    whole,
)
from d2turb.app.jobs import (
    CLIP_SIM_FRAMES,
    Progress,
    clip_argv,
    clip_simulate_argv,
    restore_argv,
    run_command,
    simulate_argv,
    write_command,
)
from d2turb.app.views import PREVIEW_SIDE, flow_view, niqe_or_reason, preview
from d2turb.app.workspace import Workspace, bundle
from d2turb.defaults import DEFAULT_DR0, DEFAULT_OVERLAP_PX, DEFAULT_TILE_PX, MEASURED_TEMPORAL
from d2turb.depth import depth_for_image
from d2turb.depth.io import DEPTH_SUFFIXES
from d2turb.errors import D2TurbError
from d2turb.io import IMAGE_SUFFIXES, image_size, read_image, write_image
from d2turb.models.hub import resolve_weights
from d2turb.sim import depth_modulation, derived_quantities, make_params
from d2turb.video import VIDEO_SUFFIXES, iter_video, video_size


# ---- simulate --------------------------------------------------------------------------------------------------
@dataclass
class SimOutput:
    turb: Path
    tilt: Path
    flow: Path  # colour-wheel picture
    depth: Path | None
    modulation: Path
    derived: dict
    command: str
    files: list[Path]
    run_dir: Path
    flow_scale_px: float = 0.0
    warnings: list[str] = field(default_factory=list)


def _prepare_sim_input(s: SimSettings, run: Path, limits: Limits) -> tuple[str, torch.Tensor]:
    if s.source == "sample":
        image = sample_image(s.sample)
        name = f"{s.sample}.png"
        write_image(run / name, image)  # 8-bit, as the command line will read it
    elif s.source == "upload":
        if not s.upload:
            raise D2TurbError("image source 'upload': upload an image first (or choose a sample)")
        src = Path(s.upload)
        if src.suffix.lower() not in IMAGE_SUFFIXES:
            raise D2TurbError(f"{src.name}: not an image file type ({known(IMAGE_SUFFIXES)})")
        w, h = image_size(src)
        check_pixels(src.name, w, h, limits.sim_pixels)
        name = safe_stem(src.name) + src.suffix.lower()
        shutil.copyfile(src, run / name)  # the original bytes: the command line reads exactly what the app read
    else:
        raise D2TurbError(f"image source must be one of {', '.join(IMAGE_SOURCES)}, got {s.source!r}")
    return name, read_image(run / name)


def run_simulation(
    s: SimSettings, workspace: Workspace, limits: Limits | None = None, progress: Progress | None = None
) -> SimOutput:
    """Simulate turbulence as the page asks: runs its ``d2turb simulate`` command in a fresh run folder and
    prepares the pictures (I_turb, I_tilt, flow, depth, M), the derived quantities and the downloads."""
    limits = limits or Limits()
    run = workspace.new_run("simulate")
    name, image = _prepare_sim_input(s, run, limits)
    stem = Path(name).stem
    depth_name = None
    if s.depth == "upload" and s.depth_upload:
        src = Path(s.depth_upload)
        if src.suffix.lower() not in DEPTH_SUFFIXES:
            raise D2TurbError(f"{src.name}: not a depth map file type ({known(DEPTH_SUFFIXES)})")
        depth_name = f"{stem}_depthmap{src.suffix.lower()}"
        shutil.copyfile(src, run / depth_name)
    values = sim_values(s, depth_name)
    # check what the job will meet before running it, with the user's file names in messages
    params = values.params()
    depth_spec = str(run / depth_name) if values.depth == depth_name else values.depth
    depth = depth_for_image(depth_spec, run / name, image, is_disparity=values.disparity)  # refuses another aspect
    argv = simulate_argv(values, name)
    run_command(argv, run, progress)
    command = write_command(run / "command.sh", argv)

    out = run / "out"
    meta = json.loads((out / f"{stem}_meta.json").read_text())
    flow = torch.from_numpy(np.load(out / f"{stem}_fwd_flow_px.npy"))
    views = run / "views"
    modulation = depth_modulation(depth[None], params.modulation, params.offset_s)[0] if depth is not None else None
    if modulation is None:
        modulation = torch.ones(1, *image.shape[-2:])
    flow_png, scale = flow_view(flow, views / "flow.png")
    result = SimOutput(
        turb=preview(read_image(out / f"{stem}_turb.png"), views / "turb.png", out / f"{stem}_turb.png"),
        tilt=preview(read_image(out / f"{stem}_tilt.png"), views / "tilt.png", out / f"{stem}_tilt.png"),
        flow=flow_png,
        depth=preview(depth, views / "depth.png") if depth is not None else None,
        modulation=preview(modulation, views / "modulation.png"),
        derived=derived_quantities(params, meta["mean_modulation"]),
        command=command,
        files=[],
        run_dir=run,
        flow_scale_px=scale,
    )
    zipped = bundle(run, f"d2turb_simulate_{stem}")
    result.files = [zipped, *(out / f"{stem}_{k}" for k in ("turb.png", "tilt.png", "fwd_flow_px.npy", "meta.json"))]
    result.files.append(run / "command.sh")
    return result


# ---- restore ---------------------------------------------------------------------------------------------------
@dataclass
class RestoreOutput:
    before: Path
    after: Path
    flow: Path
    niqe: dict
    command: str
    files: list[Path]
    run_dir: Path
    frames: int = 1
    flow_scale_px: float = 0.0
    notes: list[str] = field(default_factory=list)


def _video_frames(src: Path, path: Path, limits: Limits) -> tuple[int, int, int]:
    """(frames, width, height) of a video upload within the app's frame limit; containers that do not store the
    count (mkv, webm) are counted by decoding."""
    frames, w, h = video_size(path)
    if frames == 0:
        frames = sum(1 for _ in iter_video(path))
    if frames > limits.video_frames:
        raise D2TurbError(
            f"{src.name}: {frames} frames is more than the app takes ({limits.video_frames}); "
            "trim the video or use the command line"
        )
    return frames, w, h


def run_restore(
    upload: str | None,
    weights: str,
    workspace: Workspace,
    tile: int = DEFAULT_TILE_PX,
    overlap: int = DEFAULT_OVERLAP_PX,
    device: str = "cpu",
    limits: Limits | None = None,
    progress: Progress | None = None,
) -> RestoreOutput:
    """Restore an uploaded image or short video with its ``d2turb restore`` command (same tiling; its tqdm bars
    go to ``progress``); ``weights``: "input", a name from :func:`~d2turb.app.forms.weights_choices` or a
    .safetensors path."""
    limits = limits or Limits()
    if not upload:
        raise D2TurbError("upload an image or a short video first")
    src = Path(upload)
    if not src.is_file():
        raise D2TurbError(f"{src.name}: the uploaded file is gone; upload it again")
    weights = str(weights or "").strip()
    if not weights:
        raise D2TurbError("choose weights (or 'input' for the identity baseline)")
    resolved = resolve_weights(weights)  # one-line error for a missing name or file
    if isinstance(resolved, Path) and weights != resolved.stem:
        weights = str(resolved.resolve())  # a path: absolute, so the command works from any folder
    tile, overlap = whole("tile", tile), whole("overlap", overlap)

    is_video = src.suffix.lower() in VIDEO_SUFFIXES
    if is_video:
        frames, w, h = video_size(src)
        if frames > limits.video_frames:
            raise D2TurbError(
                f"{src.name}: {frames} frames is more than the app takes ({limits.video_frames}); "
                "trim the video or use the command line"
            )
    elif src.suffix.lower() in IMAGE_SUFFIXES:
        frames = 1
        w, h = image_size(src)
    else:
        raise D2TurbError(f"{src.name}: not an image or video file type ({known(IMAGE_SUFFIXES | VIDEO_SUFFIXES)})")
    check_pixels(src.name, w, h, limits.restore_pixels)

    run = workspace.new_run("restore")
    name = safe_stem(src.name) + src.suffix.lower()
    stem = Path(name).stem
    shutil.copyfile(src, run / name)
    if is_video:
        first = next((f for _, f in iter_video(run / name)), None)
        if first is None:
            raise D2TurbError(f"{src.name}: the video has no frames")
    else:
        first = read_image(run / name)
    argv = restore_argv(name, weights, tile, overlap, device)
    run_command(argv, run, progress)
    command = write_command(run / "command.sh", argv)

    out = run / "out"
    key = f"{stem}_000000" if is_video else stem
    restored = read_image(out / f"{key}_restored.png")
    flow = torch.from_numpy(np.load(out / f"{key}_bwd_flow_px.npy"))
    views = run / "views"
    flow_png, scale = flow_view(flow, views / "flow.png")
    notes = []
    if is_video:
        notes.append(f"{frames} frames restored; the page shows the first, the download holds all")
    if max(first.shape[-2:]) > PREVIEW_SIDE:
        notes.append(f"pictures in the page are downscaled to {PREVIEW_SIDE} px; downloads are full size")
    result = RestoreOutput(
        before=preview(first, views / "input.png"),
        after=preview(restored, views / "restored.png", out / f"{key}_restored.png"),
        flow=flow_png,
        niqe={"input": niqe_or_reason(first), "restored": niqe_or_reason(restored)},
        command=command,
        files=[],
        run_dir=run,
        frames=frames,
        flow_scale_px=scale,
        notes=notes,
    )
    zipped = bundle(run, f"d2turb_restore_{stem}")
    result.files = [zipped, out / f"{key}_restored.png", out / f"{key}_bwd_flow_px.npy", run / "command.sh"]
    return result


# ---- clip ------------------------------------------------------------------------------------------------------
@dataclass
class ClipOutput:
    before: Path  # the middle input frame
    after: Path  # the middle restored frame
    command: str  # the command lines that reproduce the run (simulate-video first for an image)
    files: list[Path]
    run_dir: Path
    frames: int
    notes: list[str] = field(default_factory=list)


def run_clip(
    upload: str | None,
    workspace: Workspace,
    temporal: int = MEASURED_TEMPORAL,
    dr0: float | None = None,
    limits: Limits | None = None,
    progress: Progress | None = None,
) -> ClipOutput:
    """Clip restoration in the page: an uploaded video is restored across frames (``d2turb restore --temporal``);
    an uploaded image is first made into a turbulent clip of ``CLIP_SIM_FRAMES`` frames at ``dr0``
    (``d2turb simulate-video``, wind 2 m/s, boiling 0.1) and then restored with that known D/r0. ``dr0`` empty or
    0 with a video: fusion without deblurring."""
    limits = limits or Limits()
    if not upload:
        raise D2TurbError("upload a short video (or an image to simulate a clip from) first")
    src = Path(upload)
    if not src.is_file():
        raise D2TurbError(f"{src.name}: the uploaded file is gone; upload it again")
    temporal = whole("the window", temporal, at_least=2, unit="frames")
    dr0 = float(dr0) if dr0 else None
    run = workspace.new_run("clip")
    name = safe_stem(src.name) + src.suffix.lower()
    shutil.copyfile(src, run / name)
    argvs, notes = [], []
    if src.suffix.lower() in VIDEO_SUFFIXES:
        frames, w, h = _video_frames(src, run / name, limits)
        check_pixels(src.name, w, h, limits.restore_pixels)
        clip, mp4 = name, f"{Path(name).stem}_restored.mp4"
    elif src.suffix.lower() in IMAGE_SUFFIXES:
        w, h = image_size(src)
        check_pixels(src.name, w, h, limits.sim_pixels)
        dr0 = dr0 or DEFAULT_DR0
        make_params(dr0=float(f"{dr0:g}"))  # the value the command line gives, checked here with the page's words
        argvs.append(clip_simulate_argv(name, dr0, out="clip"))
        clip, frames, mp4 = "clip/turb", CLIP_SIM_FRAMES, "turb_restored.mp4"
        notes.append(f"a {frames}-frame clip was simulated from the image at D/r0 = {dr0:g} and restored with it")
    else:
        raise D2TurbError(f"{src.name}: not a video or image file type ({known(IMAGE_SUFFIXES | VIDEO_SUFFIXES)})")
    argvs.append(clip_argv(clip, temporal, dr0))
    for argv in argvs:
        run_command(argv, run, progress)
    text = write_command(run / "command.sh", *argvs)
    out, views = run / "out", run / "views"
    restored_all = sorted(out.glob("*_restored.png"))  # frame names are zero-padded: sorted = in order
    if not restored_all:
        raise D2TurbError(f"{src.name}: the clip gave no restored frame")
    middle = len(restored_all) // 2
    restored_png = restored_all[middle]
    if src.suffix.lower() in VIDEO_SUFFIXES:
        before_img = next(f for i, f in iter_video(run / name) if i == middle)
    else:
        before_img = read_image(run / clip / restored_png.name.replace("_restored.png", ".png"))
    if not dr0:
        notes.append("no D/r0 given: the frames are registered and fused, not deblurred")
    result = ClipOutput(
        before=preview(before_img, views / "input.png"),
        after=preview(read_image(restored_png), views / "restored.png", restored_png),
        command=text,
        files=[],
        run_dir=run,
        frames=frames,
        notes=notes,
    )
    zipped = bundle(run, f"d2turb_clip_{Path(name).stem}")
    result.files = [zipped, restored_png, run / "command.sh"] + ([out / mp4] if (out / mp4).is_file() else [])
    return result
