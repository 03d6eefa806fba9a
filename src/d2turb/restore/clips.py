"""``d2turb restore CLIP --temporal N``: a clip restored across frames into a folder (:func:`restore_clip_files`),
written frame by frame as the restorer yields them. Output names: :mod:`d2turb.restore.files`."""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import os
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from d2turb.clip import ClipRestorer
from d2turb.clip.blind import BlindDeblur
from d2turb.device import limit_malloc_arenas, resolve_device
from d2turb.errors import D2TurbError, FileErrors, summary
from d2turb.io import BackgroundWriter, SharedUint8, check_output_dir, write_image, write_json, write_npy
from d2turb.io.formats import RGB8, to_restorer, to_stored
from d2turb.ops.splat import invert_flow
from d2turb.restore.clip_build import ClipOptions, clip_restorer
from d2turb.restore.clip_source import check_frame_sizes, open_clip
from d2turb.restore.compare import output_name, side_by_side
from d2turb.restore.files import no_empty_out, save_compare
from d2turb.video import VIDEO_HINT, Mp4Writer, Y4mWriter, can_write_mp4, is_stream, sigint_noted


def _kept(frames, store: dict):
    """The frames, each also kept in ``store`` under its index until the caller pops it."""
    for i, frame in enumerate(frames):
        store[i] = frame
        yield frame


def _panel(image) -> np.ndarray:
    """A restorer's input or output frame as an 8-bit RGB panel of side_by_side: (H,W,3) uint8."""
    if isinstance(image, np.ndarray) and image.dtype == np.uint8:
        return image if image.ndim == 3 and image.shape[2] == 3 else np.repeat(image.reshape(*image.shape[:2], 1), 3, 2)
    return to_stored(image, RGB8)


def restore_clip_files(
    src, out, temporal: int, options: ClipOptions | None = None, max_frames: int | None = None, **kwargs
) -> int:
    """Restore a clip across frames into the folder ``out`` (``d2turb restore --temporal``): registration to a
    sliding window of ``temporal`` frames, fusion, deblurring (:class:`~d2turb.clip.ClipRestorer`).

    NAME is the video's stem or the folder's name. Writes FRAME_restored.png per frame (a folder's frames keep
    their stems; a video's are NAME_NNNNNN), NAME_restored.mp4 (video extra), FRAME_fused.png
    (``save_intermediate``), fwd_flow_px/NNNNNN.npy (``save_flow``: float32 (2, H, W), the forward displacement Δ
    of each frame from the restored one, frame(x) ≈ restored(x + Δ(x)), px, x then y) and with ``compare``
    NAME_compare.mp4 (input | restored side by side, video extra) and NAME_compare.png (the middle frame).
    Each frame is written as it is restored; Ctrl-C (SIGINT) stops the run with the mp4 finalised on the frames
    restored so far (playable) and restore.json saying so, then raises KeyboardInterrupt (exit status 130).

    Args:
        src: a video file (also SER, FITS) or a folder of frames; the outputs keep its pixels (16 bits, grey); or a
            stream read once as it comes: ``-`` (standard input, e.g. y4m), a URL, a capture device
            (:func:`~d2turb.video.is_stream`).
        out: the output folder, or ``-``: the restored frames as a y4m stream on standard output, nothing else.
        options: :class:`ClipOptions` (None: the defaults); ``kwargs``: its fields by name, in place of those
            (``dr0=2.0, compare=True``).
        max_frames: restore at most this many frames (the first ones read).

    Returns:
        The exit status: 0, or 1 when some frames could not be read (2 when none could).
    """
    with sigint_noted():
        return _restore_clip_files(src, out, temporal, options, max_frames, **kwargs)


def _restore_clip_files(src, out, temporal: int, options, max_frames, **kwargs) -> int:
    o = ClipOptions.of(options, **kwargs)
    fps, passes, preset, fusion, png_level = o.fps, o.passes, o.preset, o.fusion_used, o.png_level
    stream = is_stream(src)
    src = os.fspath(src) if stream else Path(src)
    if not stream and not src.exists():
        raise D2TurbError(f"{src}: no such file or directory")
    if fps is not None and not (np.isfinite(fps) and fps > 0):
        raise D2TurbError(f"fps must be positive, got {fps}", param="fps")
    if max_frames is not None and max_frames < 1:
        raise D2TurbError(f"--max-frames must be at least 1, got {max_frames}")
    if stream and o.deblur == "physics" and o.dr0 is None:
        raise D2TurbError(
            f"{src}: a stream is read once, so D/r0 cannot be measured on its first frames first: give --dr0 X "
            "(or leave --deblur at auto: the blind deblur)"
        )
    to_stdout = os.fspath(out) == "-"
    if to_stdout and (o.compare or o.save_intermediate or o.save_flow):
        raise D2TurbError(
            "--out - writes only the restored frames (y4m on standard output): --compare, "
            "--save-intermediate and --save-flow need an output folder"
        )
    ClipRestorer.check_settings(temporal, passes, fusion, preset)  # bad settings first, in one line
    errors = FileErrors(2, o.fail_fast)  # per frame: a bad one is reported and skipped
    clip = open_clip(src, errors)
    check_frame_sizes(Path(src), clip.files)
    device = resolve_device(o.device)
    limit_malloc_arenas()  # before the threads of the stream start
    restorer, deblur_name, record = clip_restorer(src, temporal, dataclasses.replace(o, device=device))
    names, fmt = clip.names, clip.fmt
    read = clip.frames if max_frames is None else itertools.islice(clip.frames, max_frames)
    frames = (to_restorer(frame, fmt) for frame in read)
    fps = clip.fps or fps or 30.0
    total = clip.total if max_frames is None else min(clip.total or max_frames, max_frames)  # the bar's total
    name = clip.name
    label = clip.name if stream else src.name
    pixels = "" if fmt == RGB8 else f", {fmt.describe()} frames written as such (mp4: 8-bit RGB)"
    print(
        f"restoring {src} over windows of {temporal} frames, fusion: {fusion}, deblur: {deblur_name}{pixels}",
        file=sys.stderr,
    )
    if to_stdout:
        count = _restore_to_stdout(restorer.restore(frames), fmt, fps, label, total)
        _blind_note(restorer)
        print(f"restored {count} frame(s) of {label} to standard output (y4m)", file=sys.stderr)
        return summary("restore", count + len(errors.failed), len(errors.failed))
    out_dir = check_output_dir(out, inputs=clip.files or ([] if stream else [src]))
    mp4 = out_dir / output_name(name, "restored", "mp4")
    compare = o.compare
    side = out_dir / output_name(name, "compare", "mp4") if compare else None
    if not can_write_mp4():
        print(f"note: no mp4 written; {VIDEO_HINT}")
        mp4 = side = None
    inputs: dict[int, object] = {}  # with compare: the input frames not yet restored (bounded by the lookahead)
    if compare:
        frames = _kept(frames, inputs)
    pick, last = (total or 0) // 2, None  # NAME_compare.png: the middle frame (the last one, if fewer were read)
    count, interrupted = 0, False
    with no_empty_out(out_dir), contextlib.ExitStack() as stack:
        # one writer thread, one frame queued: the PNGs keep pace (~0.1 s a 1080p frame) at 80 MB less peak than 2 + 2
        writer = stack.enter_context(BackgroundWriter(max_pending=1, compute_device=device, threads=1))
        video = None if mp4 is None else stack.enter_context(Mp4Writer(mp4, fps))
        side_video = None if side is None else stack.enter_context(Mp4Writer(side, fps))
        restoring = restorer.restore(frames)
        try:
            for frame in tqdm(restoring, desc=label, unit="frame", total=total or None):
                stem = names[frame.index]
                restored = SharedUint8(frame.restored)  # converted once, for the PNG and the mp4
                stored = restored if fmt == RGB8 else to_stored(frame.restored, fmt)  # 16 bits, grey: as the input
                writer.submit(write_image, out_dir / output_name(stem, "restored", "png"), stored, png_level)
                if compare:
                    before = _panel(inputs.pop(frame.index))
                    if frame.index <= pick:
                        last = (before, _panel(frame.restored))
                    if side_video is not None:
                        side_video.write(side_by_side([before, _panel(frame.restored)]))
                if o.save_intermediate:
                    fused = frame.fused if fmt == RGB8 else to_stored(frame.fused, fmt)
                    writer.submit(write_image, out_dir / output_name(stem, "fused", "png"), fused, png_level)
                if o.save_flow:  # forward displacement: frame(x) ≈ restored(x + Δ(x)), the inverse of bwd_flow_px
                    fwd = invert_flow(frame.bwd_flow_px[None])[0].numpy().astype(np.float32)
                    writer.submit(write_npy, out_dir / "fwd_flow_px" / f"{frame.index:06d}.npy", fwd)
                if video is not None:
                    video.write(restored)
                count += 1
        except KeyboardInterrupt:  # the frames so far stay: the mp4 is finalised as the with block closes
            interrupted = True
            restoring.close()  # the restorer's threads stop
        if last is not None:
            writer.submit(save_compare, out_dir, name, *last, png_level)
    record = _blind_note(restorer) or record
    if count:  # a run that restored nothing leaves no folder (no_empty_out), so no restore.json either
        settings = {
            "temporal": temporal,
            "passes": passes,
            "preset": preset,
            "fusion": fusion,
            "pixels": fmt.describe(),
        }
        if max_frames is not None:
            settings["max_frames"] = max_frames
        if interrupted:
            settings["interrupted"] = True
        write_json(out_dir / "restore.json", {"input": str(src), "frames": count, **settings, "deblur": record})
    if interrupted:
        kept = f"; {mp4.name} finalised with them" if mp4 and count else ""
        print(f"interrupted after {count} restored frame(s) of {label}, written into {out_dir}{kept}", file=sys.stderr)
        raise KeyboardInterrupt
    print(f"restored {count} frame(s) of {label} into {out_dir}" + (f" ({mp4.name})" if mp4 else ""))
    if compare:
        print(f"before | after: {out_dir / output_name(name, 'compare', 'png')}" + (f", {side.name}" if side else ""))
    return summary("restore", count + len(errors.failed), len(errors.failed))


def _blind_note(restorer) -> dict | None:
    """The blind deblur's record (None for another deblur), its note printed."""
    if not isinstance(restorer.deblur, BlindDeblur):
        return None
    if restorer.deblur.note:
        print(
            f"note: {restorer.deblur.note}; for the physics deblur give --dr0 X (and the optics: --aperture, "
            "--wavelength, --ifov), or --deblur none",
            file=sys.stderr,
        )
    return restorer.deblur.record


def _restore_to_stdout(restored, fmt, fps: float, label: str, total: int | None) -> int:
    """The restored frames as a y4m stream on standard output, each as it comes; returns how many."""
    pipe = Y4mWriter("-", fps, fmt.channels, fmt.bits)
    count = 0
    try:
        for frame in tqdm(restored, desc=label, unit="frame", total=total or None):
            pipe.write(to_stored(frame.restored, fmt))
            count += 1
    finally:
        pipe.close()
    return count
