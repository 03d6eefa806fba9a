"""Where ``d2turb restore CLIP --temporal N`` writes a restored clip, each frame as the restorer yields it: a folder
(:class:`FolderOut`) or standard output (:class:`StdoutOut`). Both are context managers with one ``write(frame)`` a
frame; what a run ends with (the mp4 finalised, restore.json, the closing line) is theirs too. Output names:
:func:`d2turb.restore.compare.output_name`."""

from __future__ import annotations

import contextlib
import sys

import numpy as np

from d2turb.clip.live import LIVE_X264_PRESET, dis_preset
from d2turb.io import BackgroundWriter, SharedUint8, check_output_dir, write_image, write_json, write_npy
from d2turb.io.formats import RGB8, to_stored
from d2turb.ops.splat import invert_flow
from d2turb.restore.compare import output_name, save_compare, side_by_side
from d2turb.restore.files import no_empty_out
from d2turb.video import VIDEO_HINT, X264_PRESET, Mp4Writer, Y4mWriter, can_write_mp4


def _panel(image) -> np.ndarray:
    """A restorer's input or output frame as an 8-bit RGB panel of side_by_side: (H,W,3) uint8."""
    if isinstance(image, np.ndarray) and image.dtype == np.uint8:
        return image if image.ndim == 3 and image.shape[2] == 3 else np.repeat(image.reshape(*image.shape[:2], 1), 3, 2)
    return to_stored(image, RGB8)


class FolderOut:
    """A restored clip into the folder ``out`` (see :func:`~d2turb.restore.clips.restore_clip_files`):
    FRAME_restored.png a frame in the clip's format (the live preset: only where no mp4 is written), NAME_restored.mp4
    (video extra; the live preset's at x264 ``LIVE_X264_PRESET``), and with the options
    ``compare`` NAME_compare.mp4 and NAME_compare.png (the middle frame), ``save_intermediate`` FRAME_fused.png,
    ``save_flow`` fwd_flow_px/NNNNNN.npy. A folder that the run leaves empty is removed."""

    def __init__(self, out, clip, options, fps: float, device):
        self.names, self.fmt, self.name = clip.names, clip.fmt, clip.name
        self.o, self.fps, self.device = options, fps, device
        self.dir = check_output_dir(out, inputs=clip.inputs)
        self.mp4 = self.dir / output_name(clip.name, "restored", "mp4")
        self.side = self.dir / output_name(clip.name, "compare", "mp4") if options.compare else None
        if not can_write_mp4():
            print(f"note: no mp4 written; {VIDEO_HINT}")
            self.mp4 = self.side = None
        # the live preset writes the mp4 alone (x264 ultrafast; a PNG a frame would take a core of its own at 720p),
        # or the PNGs where no mp4 can be written
        self.live = dis_preset(options.preset) is None
        self.frame_pngs = not self.live or self.mp4 is None
        self._inputs: dict[int, object] = {}  # with compare: the input frames not yet restored (the lookahead's)
        self._pick, self._last = (clip.total or 0) // 2, None  # NAME_compare.png: the middle frame (or the last)

    def __enter__(self):
        self._stack = stack = contextlib.ExitStack()
        stack.enter_context(no_empty_out(self.dir))
        # one writer thread, one frame queued: the PNGs keep pace (~0.1 s a 1080p frame) at 80 MB less peak than 2 + 2
        self.writer = stack.enter_context(BackgroundWriter(max_pending=1, compute_device=self.device, threads=1))
        preset = LIVE_X264_PRESET if self.live else X264_PRESET
        self.video = None if self.mp4 is None else stack.enter_context(Mp4Writer(self.mp4, self.fps, preset))
        self.side_video = None if self.side is None else stack.enter_context(Mp4Writer(self.side, self.fps))
        return self

    def __exit__(self, *exc):
        return self._stack.__exit__(*exc)  # the writer's queue drained, the mp4s finalised, an empty folder removed

    def finish(self) -> None:
        """NAME_compare.png, once the frames are written (also after Ctrl-C: of the frames so far)."""
        if self._last is not None:
            self.writer.submit(save_compare, self.dir, self.name, *self._last, self.o.png_level)

    def inputs(self, frames):
        """The restorer's input frames, each kept (with ``compare``) until its restored frame is written."""
        for i, frame in enumerate(frames):
            if self.o.compare:
                self._inputs[i] = frame
            yield frame

    def write(self, frame) -> None:
        """The outputs of one restored :class:`~d2turb.clip.ClipFrame`."""
        o, stem, level = self.o, self.names[frame.index], self.o.png_level
        restored = SharedUint8(frame.restored)  # converted once, for the PNG and the mp4
        stored = restored if self.fmt == RGB8 else to_stored(frame.restored, self.fmt)  # 16 bits, grey: as the input
        if self.frame_pngs:
            self.writer.submit(write_image, self.dir / output_name(stem, "restored", "png"), stored, level)
        if o.compare:
            before = _panel(self._inputs.pop(frame.index))
            if frame.index <= self._pick:
                self._last = (before, _panel(frame.restored))
            if self.side_video is not None:
                self.side_video.write(side_by_side([before, _panel(frame.restored)]))
        if o.save_intermediate:
            fused = frame.fused if self.fmt == RGB8 else to_stored(frame.fused, self.fmt)
            self.writer.submit(write_image, self.dir / output_name(stem, "fused", "png"), fused, level)
        if o.save_flow:  # forward displacement: frame(x) ≈ restored(x + Δ(x)), the inverse of bwd_flow_px
            fwd = invert_flow(frame.bwd_flow_px[None])[0].numpy().astype(np.float32)
            self.writer.submit(write_npy, self.dir / "fwd_flow_px" / f"{frame.index:06d}.npy", fwd)
        if self.video is not None:
            self.video.write(restored)

    def record(self, record: dict) -> None:
        """restore.json: what was restored, and how."""
        write_json(self.dir / "restore.json", record)

    def done(self, count: int, label: str, interrupted: bool) -> None:
        """The run's closing line."""
        if interrupted:
            kept = f"; {self.mp4.name} finalised with them" if self.mp4 and count else ""
            print(
                f"interrupted after {count} restored frame(s) of {label}, written into {self.dir}{kept}",
                file=sys.stderr,
            )
            return
        print(f"restored {count} frame(s) of {label} into {self.dir}" + (f" ({self.mp4.name})" if self.mp4 else ""))
        if self.o.compare:
            compare = self.dir / output_name(self.name, "compare", "png")
            print(f"before | after: {compare}" + (f", {self.side.name}" if self.side else ""))


class StdoutOut:
    """A restored clip as a y4m stream on standard output, each frame as it comes, in the clip's format; nothing
    else is written."""

    def __init__(self, clip, fps: float):
        self.fmt, self.fps = clip.fmt, fps

    def __enter__(self):
        self.pipe = Y4mWriter("-", self.fps, self.fmt.channels, self.fmt.bits)
        return self

    def __exit__(self, *exc):
        self.pipe.close()
        return False

    def inputs(self, frames):
        return frames

    def finish(self) -> None:
        """Nothing: the frames are all out."""

    def write(self, frame) -> None:
        self.pipe.write(to_stored(frame.restored, self.fmt))

    def record(self, record: dict) -> None:
        """Nothing: standard output holds the frames alone."""

    def done(self, count: int, label: str, interrupted: bool) -> None:
        what = "interrupted after" if interrupted else "restored"
        print(f"{what} {count} frame(s) of {label} to standard output (y4m)", file=sys.stderr)
