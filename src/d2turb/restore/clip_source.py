"""The reader of ``d2turb restore --temporal`` and ``evaluate --real-clips``: a clip's frames from a video file, a SER
video, a FITS image or cube, a folder of frames or a stream, each decoded once, in the layout the clip restorer
takes (:func:`~d2turb.io.formats.to_restorer`); an unreadable frame reported and skipped, a folder's frame sizes
checked from their headers first. The outputs keep the frames' pixels (grey or RGB, 8 or 16 bits:
:class:`~d2turb.io.formats.PixelFormat`)."""

from __future__ import annotations

import collections
import itertools
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from d2turb.errors import D2TurbError
from d2turb.io import named_error as _named  # an input's error, naming it
from d2turb.io.fits import is_fits, iter_fits
from d2turb.io.folder import FrameFolder, check_frame_sizes  # noqa: F401 - check_frame_sizes: importable from here
from d2turb.io.formats import PixelFormat, array_format, to_restorer
from d2turb.io.ser import iter_ser, read_ser_header
from d2turb.video import VideoSource, is_stream, is_video, stream_name

SER_SUFFIX = ".ser"
RGB_FLOAT = PixelFormat(3, 16)  # to_restorer's float32 RGB: what ``measure`` and the evaluation read


@dataclass
class Clip:
    """An open clip (:func:`open_clip`), read once. ``source`` yields each readable frame in the restorer's layout in
    ``fmt`` ((H,W,C) uint8 for 8 bits, else float32 in [0,1]) and appends its name to ``names`` (a folder's frames
    keep their stems; a video's are NAME_NNNNNN); :attr:`frames` are the first ``max_frames`` of them (None: all).
    ``name`` names the outputs, ``label`` the progress lines; ``fmt`` is what the outputs are written in; ``fps``
    None for a folder; ``total`` None where unknown; ``inputs`` the files read (none for a stream)."""

    name: str
    label: str
    fmt: PixelFormat
    source: Iterator[np.ndarray]
    names: list[str] = field(default_factory=list)
    fps: float | None = None
    total: int | None = None
    inputs: list[Path] = field(default_factory=list)
    max_frames: int | None = None
    report: _Report | None = None

    @property
    def frames(self) -> Iterator[np.ndarray]:
        """The frames to restore: the first ``max_frames`` (after :meth:`head`, its frames first)."""
        return itertools.islice(self.source, self.max_frames)

    def head(self, n: int) -> list[np.ndarray]:
        """The source's first ``n`` frames (fewer in a shorter clip; more than ``max_frames`` where n is larger: a
        measurement's), decoded once: the source yields them again, each let go as it is yielded, and the bad frames
        met among them are reported then, in their place (a run that stops before restoring reports none)."""
        self.report.held = held = []
        for frame in itertools.islice(self.source, n):
            held.append(frame)
        self.report.held = None
        self.source = _replayed(collections.deque(held), self.source, self.report.errors)
        return [f for f in held if not isinstance(f, BaseException)]


def _replayed(kept: collections.deque, rest: Iterator, errors) -> Iterator:
    while kept:
        item = kept.popleft()
        if isinstance(item, BaseException):
            errors.record(item)
        else:
            yield item
    yield from rest


@dataclass
class _Report:
    """Where a clip's readers report a bad frame: to ``errors``, up to the ``limit``-th readable frame (a bad frame
    after it is read only by a measurement's head, not restored: not reported); while :meth:`Clip.head` reads, held
    in ``held`` (between the frames) until they are given again."""

    errors: object
    names: list[str]
    limit: int | None = None
    held: list | None = None

    def record(self, exc: D2TurbError) -> None:
        if self.limit is not None and len(self.names) >= self.limit:
            return
        if self.held is not None:
            self.held.append(exc)
        else:
            self.errors.record(exc)


def is_clip_file(src: Path) -> bool:
    """A file read as a whole clip: a video, a SER video or a FITS image or cube."""
    return is_video(src) or (src.is_file() and (src.suffix.lower() == SER_SUFFIX or is_fits(src)))


def _numbered(stem: str, frames, errors, label) -> Iterator[tuple[str, np.ndarray]]:
    """(NAME_NNNNNN, frame) of a video's frames; a clip that stops decoding ends there, reported."""
    try:
        for i, frame in enumerate(frames):
            yield f"{stem}_{i:06d}", frame
    except D2TurbError as exc:
        errors.record(_named(label, exc))


def _restorer_frames(named, fmt: PixelFormat, names: list[str]) -> Iterator[np.ndarray]:
    for name, frame in named:
        names.append(name)
        yield to_restorer(frame, fmt)


def open_clip(src, errors, max_frames: int | None = None) -> Clip:
    """Open the clip ``src`` for reading: a path (see the module), or a stream (``-``, a URL, a capture device:
    :func:`~d2turb.video.is_stream`) decoded as it comes; ``errors.record`` gets each unreadable frame; at most
    ``max_frames`` frames are read (None: all).

    Raises:
        D2TurbError: no such input, not a clip, an empty folder or one whose frames differ in size (from their
        headers), a SER or FITS file that cannot be read.
    """
    stream = is_stream(src)
    src = src if stream else Path(src)
    if not stream and not src.exists():
        raise D2TurbError(f"{src}: no such file or directory")
    name, label, inputs = (stream_name(src), stream_name(src), []) if stream else (src.stem, src.name, [src])
    fps = total = named = None  # named: (frame name, frame as stored) pairs
    names: list[str] = []
    report = _Report(errors, names, max_frames)
    if stream or is_video(src):  # a stream is read once, as it comes
        video = VideoSource(src)
        fmt, fps, total, frames = PixelFormat(video.channels, video.bits), video.fps, video.frames or None, video
    elif src.is_file() and src.suffix.lower() == SER_SUFFIX:
        header = read_ser_header(src)
        fmt, fps, total = PixelFormat(header.channels, 8 if header.depth <= 8 else 16), header.fps, header.frames
        frames = iter_ser(src, header)
    elif src.is_file() and is_fits(src):
        cube = iter_fits(src)
        first = next(cube)  # one read of the file (the cube is held by astropy either way)
        fmt, frames = array_format(first), itertools.chain([first], cube)
    elif src.is_dir():
        named = FrameFolder(src, report)  # its frames keep their stems
        name, fmt, total, inputs = src.resolve().name, named.fmt, len(named.files), named.files
    else:
        raise D2TurbError(f"{src}: a clip is a video file (or SER, FITS) or a folder of frames")
    if max_frames is not None:
        total = min(total or max_frames, max_frames)
    if named is None:  # a video's frames are NAME_NNNNNN
        named = _numbered(name, frames, report, src)
    return Clip(name, label, fmt, _restorer_frames(named, fmt, names), names, fps, total, inputs, max_frames, report)


def rgb_tensor(frame: np.ndarray) -> torch.Tensor:
    """A frame in the restorer's layout as a (3,H,W) float32 RGB tensor in [0,1] (what ``measure`` and the
    evaluation read)."""
    return torch.from_numpy(to_restorer(frame, RGB_FLOAT).transpose(2, 0, 1).copy())


def clip_frames(src: Path, errors, as_stored: bool = False) -> tuple[list[str], object]:
    """(frame names, iterator of frames) of a clip (:func:`open_clip`). ``as_stored``: as the clip restorer takes
    them in the clip's format (:func:`~d2turb.io.formats.to_restorer`: (H,W,C) uint8 for 8 bits, else float32);
    else (3,H,W) float32 RGB tensors in [0,1] (:func:`rgb_tensor`)."""
    clip = open_clip(src, errors)
    return clip.names, (clip.frames if as_stored else map(rgb_tensor, clip.frames))
