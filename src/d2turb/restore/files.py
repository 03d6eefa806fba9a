"""Restored files from image files and videos, frame by frame with a model: what ``d2turb restore`` writes (a clip
restored across frames, ``--temporal``: :mod:`d2turb.restore.clips`). The commands and the page both run these.

One naming rule (docs/cli.md, :func:`d2turb.restore.compare.output_name`): every output is named after its input,
``NAME_<what>.<ext>``, NAME being an image's or a video's file stem, or a folder clip's folder name:
``NAME_restored.png`` (an image, a frame: a video's frames are NAME_NNNNNN), ``NAME_restored.mp4`` (a video, a
clip), ``NAME_compare.png`` / ``NAME_compare.mp4`` (``--compare``), ``NAME_bwd_flow_px.npy`` (the backward flow V̂:
warp(NAME_deblurred, V̂) ≈ NAME_restored), ``NAME_deblurred.png``, ``NAME_fused.png``; a clip's flows are
``fwd_flow_px/NNNNNN.npy`` (forward: frame(x) ≈ restored(x + Δ(x))). Earlier versions named both ``flow``."""

from __future__ import annotations

import contextlib
import dataclasses
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from d2turb.defaults import DEFAULT_OVERLAP_PX, DEFAULT_TILE_PX
from d2turb.device import resolve_device
from d2turb.errors import D2TurbError
from d2turb.io import (
    FileJob,
    check_output_dir,
    check_unique_stems,
    expand_inputs,
    read_image,
    write_image,
    write_npy,
)
from d2turb.io.fits import is_fits, read_fits_image
from d2turb.io.formats import RGB8, PixelFormat, array_format, image_format, to_restorer, to_stored
from d2turb.io.jobs import JobOptions  # the options of every file job
from d2turb.io.read import read_stored
from d2turb.restore.compare import output_name, save_compare, side_by_side
from d2turb.restore.single import Restorer
from d2turb.video import Mp4Writer, can_write_mp4, is_video, iter_video, video_fps, video_size


def split_inputs(inputs: list) -> tuple[list[Path], list[Path]]:
    """(image files, video files) of ``inputs`` (files and folders); output names must be unique."""
    images, videos = [], []
    for item in inputs:
        p = Path(item)
        if is_video(p):
            videos.append(p)
        else:
            images.extend(expand_inputs([item]))
    check_unique_stems(images + videos)
    return images, videos


def read_input(path: Path) -> tuple:
    """An input image as the model restores it, (3,H,W) float32 in [0,1], and the :class:`PixelFormat` its outputs
    are written in (16-bit and grey inputs give 16-bit and grey outputs; a FITS file: its image)."""
    if path.suffix.lower() == ".ser":
        raise D2TurbError(f"{path}: a SER video is restored as a clip: give --temporal N")
    if is_fits(path):
        arr = read_fits_image(path)
    else:
        fmt = image_format(path)
        if fmt is None or fmt == RGB8:
            return read_image(path), RGB8
        arr = read_stored(path)
    rgb = to_restorer(arr, PixelFormat(3, 16))  # float32 (H,W,3)
    return torch.from_numpy(rgb.transpose(2, 0, 1).copy()), array_format(arr)


def _save(
    out_dir: Path, stem: str, details: dict, save_flow: bool, save_intermediate: bool, png_level: int, fmt=RGB8
) -> None:
    def stored(image):
        return image if fmt == RGB8 else to_stored(image, fmt)

    write_image(out_dir / output_name(stem, "restored", "png"), stored(details["restored"]), png_level)
    if save_flow:
        write_npy(out_dir / output_name(stem, "bwd_flow_px", "npy"), details["bwd_flow_px"].numpy().astype(np.float32))
    if save_intermediate:
        write_image(out_dir / output_name(stem, "deblurred", "png"), stored(details["deblurred"]), png_level)


@contextlib.contextmanager
def no_empty_out(out_dir: Path):
    """A run that leaves ``out_dir`` empty (it failed before writing anything, or wrote nothing) removes it, when it
    did not exist before the run: no empty output folder is left behind."""
    existed = out_dir.exists()
    try:
        yield
    finally:
        if not existed:
            with contextlib.suppress(OSError):
                out_dir.rmdir()  # only when empty


def video_frame_count(path: Path) -> int | None:
    """Frame count stored in a video's container (None when it stores none or cannot be read: the bar counts up)."""
    try:
        return video_size(path)[0] or None
    except D2TurbError:
        return None


@dataclasses.dataclass(frozen=True)
class RestoreOptions(JobOptions):
    """The options of :func:`restore_files` (``d2turb restore``), besides :class:`~d2turb.io.JobOptions`'s device,
    save_flow, png_level and fail_fast.

    Args:
        tile, overlap: tiling of large images, px (a model's deblur).
        save_intermediate: also write NAME_deblurred.png (a clip's: FRAME_fused.png).
        compare: also write NAME_compare.png (input | restored, labelled) and for a video or clip NAME_compare.mp4.
    """

    tile: int = DEFAULT_TILE_PX
    overlap: int = DEFAULT_OVERLAP_PX
    save_intermediate: bool = False
    compare: bool = False


def restore_files(inputs: list, out, weights=None, options: RestoreOptions | None = None, **kwargs) -> int:
    """Restore images, folders of images and videos (frame by frame) with a model into the folder ``out``.

    Writes NAME_restored.png per image (a video's frames: NAME_NNNNNN_restored.png, and NAME_restored.mp4 with the
    video extra), NAME_bwd_flow_px.npy (``save_flow``: float32 (2, H, W), the predicted backward flow V̂ in px, x then
    y: warp(NAME_deblurred, V̂) ≈ NAME_restored)
    and NAME_deblurred.png (``save_intermediate``: Î_tilt); with ``compare``, NAME_compare.png (input | restored,
    labelled; a video's of its middle frame) and for a video NAME_compare.mp4 (side by side). An unreadable input
    is reported in one ``error:`` line and skipped (``fail_fast``: raised).

    Args:
        weights: as :class:`~d2turb.restore.Restorer` takes them (None: the recommended shipped model).
        options: :class:`RestoreOptions` (None: the defaults); ``kwargs``: any of its fields by name (``tile=256``),
            in place of the value in ``options``.

    Returns:
        The exit status: 0 all done, 1 some inputs failed, 2 all failed.
    """
    o = RestoreOptions.of(options, **kwargs)
    tile, overlap, device, compare, png_level = o.tile, o.overlap, o.device, o.compare, o.png_level
    images, videos = split_inputs(inputs)
    out_dir = check_output_dir(out, inputs=images + videos)
    restorer = Restorer(weights, device=resolve_device(device), tile=tile, overlap=overlap, progress=True)
    job = FileJob("restore", len(images) + len(videos), o.fail_fast, max_pending=4, compute_device=restorer.device)
    saved = (o.save_flow, o.save_intermediate, png_level)
    count = 0

    def restored(path: Path) -> tuple:
        image, fmt = read_input(path)
        job.before_compute()
        return image, restorer.restore_with_details(image), fmt

    with no_empty_out(out_dir), job:
        for path, (image, details, fmt) in job.each(images, restored, named=True, desc="restore", unit="img"):
            job.submit(_save, out_dir, path.stem, details, *saved, fmt)
            if compare:
                job.submit(save_compare, out_dir, path.stem, image, details["restored"], png_level)
            count += 1
        for video in videos:
            total = video_frame_count(video)
            bar = tqdm(iter_video(video), desc=video.name, unit="frame", total=total)
            frames = iter(bar)
            pick = (total or 0) // 2  # the frame of NAME_compare.png
            with contextlib.ExitStack() as stack:
                mp4 = side = None
                if can_write_mp4():  # the restored clip as a video too, at the input's frame rate
                    fps = video_fps(video)
                    mp4 = stack.enter_context(Mp4Writer(out_dir / output_name(video.stem, "restored", "mp4"), fps))
                    if compare:
                        side = stack.enter_context(Mp4Writer(out_dir / output_name(video.stem, "compare", "mp4"), fps))
                while True:
                    try:
                        i, frame = next(frames, (None, None))
                        if frame is None:
                            break
                        job.before_compute()
                        details = restorer.restore_with_details(frame)
                    except D2TurbError as exc:
                        bar.close()
                        job.record(exc, video)
                        break
                    job.submit(_save, out_dir, f"{video.stem}_{i:06d}", details, *saved)
                    if compare and i == pick:
                        job.submit(save_compare, out_dir, video.stem, frame, details["restored"], png_level)
                    if mp4 is not None:
                        mp4.write(details["restored"])
                    if side is not None:
                        side.write(side_by_side([frame, details["restored"]]))
                    count += 1
                if mp4 is not None and not mp4.frames:
                    stack.pop_all()
                    mp4.abort()
                    if side is not None:
                        side.abort()
    print(f"restored {count} image(s) with {restorer.name} into {out_dir}")
    return job.finish()
