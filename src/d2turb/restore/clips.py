"""``d2turb restore CLIP --temporal N``: a clip restored across frames (:func:`restore_clip_files`), top-down: the
reader yields the frames (:func:`~d2turb.restore.clip_source.open_clip`), the restorer restores them
(:func:`~d2turb.restore.clip_build.clip_restorer`), the writer writes each as it comes
(:mod:`d2turb.restore.clip_out`: a folder, or y4m on standard output)."""

from __future__ import annotations

import dataclasses
import os
import sys

import numpy as np
from tqdm import tqdm

from d2turb.clip.blind import BlindDeblur
from d2turb.clip.frames import stream_lookahead
from d2turb.device import limit_malloc_arenas, resolve_device
from d2turb.errors import D2TurbError, FileErrors, summary
from d2turb.io.formats import RGB8
from d2turb.restore.clip_build import ClipOptions, check_clip_settings, clip_restorer
from d2turb.restore.clip_out import FolderOut, StdoutOut
from d2turb.restore.clip_source import open_clip
from d2turb.video import is_stream, sigint_noted


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
            (:func:`~d2turb.video.is_stream`), whose output t waits for input t + ``options.lookahead`` at most
            (default temporal/2 − 1: :func:`~d2turb.clip.frames.stream_lookahead`).
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
    if o.lookahead is None and is_stream(src):  # an output waits for the input half a window later, not 1.5 windows
        o = dataclasses.replace(o, lookahead=stream_lookahead(temporal))
    to_stdout = os.fspath(out) == "-"
    _check_request(src, o, max_frames, to_stdout)  # before a stream is opened: it may wait for its first bytes
    check_clip_settings(temporal, o)  # bad settings first, in one line
    errors = FileErrors(2, o.fail_fast)  # per frame: a bad one is reported and skipped
    clip = open_clip(src, errors, max_frames)
    device = resolve_device(o.device)
    limit_malloc_arenas()  # before the threads of the stream start
    restorer, deblur_name, record = clip_restorer(clip, temporal, dataclasses.replace(o, device=device))
    fps = clip.fps or o.fps or 30.0
    pixels = "" if clip.fmt == RGB8 else f", {clip.fmt.describe()} frames written as such (mp4: 8-bit RGB)"
    print(
        f"restoring {src} over windows of {temporal} frames, fusion: {o.fusion_used}, deblur: {deblur_name}{pixels}",
        file=sys.stderr,
    )
    out = StdoutOut(clip, fps) if to_stdout else FolderOut(out, clip, o, fps, device)
    count, interrupted = 0, False
    with out:
        restoring = restorer.restore(out.inputs(clip.frames))
        try:
            for frame in tqdm(restoring, desc=clip.label, unit="frame", total=clip.total or None):
                out.write(frame)
                count += 1
        except KeyboardInterrupt:  # the frames so far stay: the mp4 is finalised as the with block closes
            interrupted = True
            restoring.close()  # the restorer's threads stop
        out.finish()
    record = _blind_note(restorer) or record
    if count:  # a run that restored nothing leaves no folder, so no restore.json either
        settings = {"temporal": temporal, "passes": o.passes, "preset": o.preset, "fusion": o.fusion_used}
        settings["pixels"] = clip.fmt.describe()
        if max_frames is not None:
            settings["max_frames"] = max_frames
        if getattr(restorer, "lookahead", None) is not None:  # the clip room's (the live preset's are its own)
            settings["lookahead"] = restorer.lookahead
        if interrupted:
            settings["interrupted"] = True
        out.record({"input": str(src), "frames": count, **settings, "deblur": record})
    out.done(count, clip.label, interrupted)
    if interrupted:
        raise KeyboardInterrupt
    return summary("restore", count + len(errors.failed), len(errors.failed))


def _check_request(src, o: ClipOptions, max_frames, to_stdout: bool) -> None:
    """D2TurbError, in one line, for a request refused before anything is read."""
    stream = is_stream(src)
    if not stream and not os.path.exists(src):
        raise D2TurbError(f"{src}: no such file or directory")
    if o.fps is not None and not (np.isfinite(o.fps) and o.fps > 0):
        raise D2TurbError(f"fps must be positive, got {o.fps}", param="fps")
    if max_frames is not None and max_frames < 1:
        raise D2TurbError(f"--max-frames must be at least 1, got {max_frames}")
    if stream and o.deblur == "physics" and o.dr0 is None:
        raise D2TurbError(
            f"{src}: a stream is read once, so D/r0 cannot be measured on its first frames first: give --dr0 X "
            "(or leave --deblur at auto: the blind deblur)"
        )
    if to_stdout and (o.compare or o.save_intermediate or o.save_flow):
        raise D2TurbError(
            "--out - writes only the restored frames (y4m on standard output): --compare, "
            "--save-intermediate and --save-flow need an output folder"
        )


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
