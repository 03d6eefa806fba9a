"""A clip's frames as ``d2turb restore --temporal`` and ``evaluate --real-clips`` read them: a video file, a SER
video, a FITS image or cube, or a folder of frames; an unreadable frame reported and skipped, the frames' sizes
checked from their headers first. Frames keep their pixels as stored (grey or RGB, 8 or 16 bits:
:class:`~d2turb.io.formats.PixelFormat`), which the outputs are written in."""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageOps

from d2turb.errors import D2TurbError
from d2turb.io import list_images
from d2turb.io import named_error as _named  # an input's error, naming it
from d2turb.io.fits import is_fits, iter_fits
from d2turb.io.formats import PixelFormat, array_format, image_format, read_stored, to_restorer
from d2turb.io.ser import iter_ser, read_ser_header
from d2turb.video import VideoSource, is_stream, is_video, stream_name

SER_SUFFIX = ".ser"


@dataclass
class Clip:
    """An open clip. ``frames`` yields each readable frame as stored ((H,W) or (H,W,3), uint8, uint16 or float32
    in [0,1]) and appends its name to ``names`` (a folder's frames keep their stems; a video's are NAME_NNNNNN);
    ``fmt`` is what the outputs are written in; ``fps`` None for a folder; ``total`` None where unknown."""

    name: str
    fmt: PixelFormat
    frames: Iterator[np.ndarray]
    names: list[str] = field(default_factory=list)
    fps: float | None = None
    total: int | None = None
    files: list[Path] = field(default_factory=list)


def is_clip_file(src: Path) -> bool:
    """A file read as a whole clip: a video, a SER video or a FITS image or cube."""
    return is_video(src) or (src.is_file() and (src.suffix.lower() == SER_SUFFIX or is_fits(src)))


def _numbered(src_name: str, frames, names: list[str], errors, label) -> Iterator[np.ndarray]:
    try:
        for i, frame in enumerate(frames):
            names.append(f"{src_name}_{i:06d}")
            yield frame
    except D2TurbError as exc:  # a clip that stops decoding ends there, reported
        errors.record(_named(label, exc))


def open_clip(src, errors) -> Clip:
    """Open the clip ``src`` for reading: a path (see the module), or a stream (``-``, a URL, a capture device:
    :func:`~d2turb.video.is_stream`) decoded as it comes; ``errors.record`` gets each unreadable frame.

    Raises:
        D2TurbError: no such input, not a clip, an empty folder, a SER or FITS file that cannot be read.
    """
    names: list[str] = []
    if is_stream(src):  # read once, as it comes
        video = VideoSource(src)
        name = stream_name(src)
        frames = _numbered(name, video, names, errors, src)
        return Clip(name, PixelFormat(video.channels, video.bits), frames, names, video.fps, video.frames or None)
    src = Path(src)
    if not src.exists():
        raise D2TurbError(f"{src}: no such file or directory")
    if src.is_file() and src.suffix.lower() == SER_SUFFIX:
        header = read_ser_header(src)
        fmt = PixelFormat(header.channels, 8 if header.depth <= 8 else 16)
        frames = _numbered(src.stem, iter_ser(src, header), names, errors, src)
        return Clip(src.stem, fmt, frames, names, header.fps, header.frames)
    if src.is_file() and is_fits(src):
        cube = iter_fits(src)
        first = next(cube)  # one read of the file (the cube is held by astropy either way)
        frames = _numbered(src.stem, itertools.chain([first], cube), names, errors, src)
        return Clip(src.stem, array_format(first), frames, names, None, None)
    if is_video(src):
        video = VideoSource(src)
        fmt = PixelFormat(video.channels, video.bits)
        frames = _numbered(src.stem, video, names, errors, src)
        return Clip(src.stem, fmt, frames, names, video.fps, video.frames or None)
    if not src.is_dir():
        raise D2TurbError(f"{src}: a clip is a video file (or SER, FITS) or a folder of frames")
    files = list_images(src)
    if not files:
        raise D2TurbError(f"{src}: no images in the folder")
    fmt = None
    for f in files:  # from the headers: grey only if every frame is, 16 bits if any frame is
        found = image_format(f)
        if found is not None:
            fmt = found if fmt is None else fmt.joined(found)

    def read():
        for f in files:
            try:
                frame = read_stored(f)
            except D2TurbError as exc:
                errors.record(_named(f, exc))
                continue
            names.append(f.stem)
            yield frame

    return Clip(src.resolve().name, fmt or PixelFormat(), read(), names, None, len(files), files)


def clip_frames(src: Path, errors, as_stored: bool = False) -> tuple[list[str], object]:
    """(frame names, iterator of frames) of a clip (:func:`open_clip`). ``as_stored``: as the clip restorer takes
    them in the clip's format (:func:`~d2turb.io.formats.to_restorer`: (H,W,C) uint8 for 8 bits, else float32);
    else (3,H,W) float32 RGB tensors in [0,1] (what ``measure`` and the evaluation read)."""
    clip = open_clip(src, errors)
    rgb = PixelFormat(3, 16)  # float32 RGB
    if as_stored:
        return clip.names, (to_restorer(frame, clip.fmt) for frame in clip.frames)
    return clip.names, (torch.from_numpy(to_restorer(f, rgb).transpose(2, 0, 1).copy()) for f in clip.frames)


def _header_size(path: Path) -> tuple[int, int] | None:
    """(width, height) of an image as read_image will give it (EXIF rotation applied), from its header only;
    None when the header cannot be read (the restoring pass reports the file)."""
    try:
        with Image.open(path) as im:
            width, height = im.size
            if im.getexif().get(ImageOps.ExifTags.Base.Orientation) in (5, 6, 7, 8):
                width, height = height, width
            return width, height
    except Exception:  # noqa: BLE001 - any unreadable header: left to read_image, which reports it in one line
        return None


def check_frame_sizes(src: Path, files: list[Path]) -> None:
    """A folder clip's frames must have one size: checked from the headers before anything is measured or
    written, so that a mismatch is one error line and leaves nothing behind."""
    first = None
    for f in files:
        size = _header_size(f)
        if size is None:
            continue
        if first is None:
            first = (f, size)
        elif size != first[1]:
            raise D2TurbError(
                f"{src}: frame {f.name} is {size[0]}x{size[1]}, the first ({first[0].name}) is "
                f"{first[1][0]}x{first[1][1]}: all frames of a clip must have one size"
            )
