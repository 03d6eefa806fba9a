"""A folder of frames read as one clip (:class:`FrameFolder`): its image files in order, one size checked from their
headers before anything is decoded, the :class:`~d2turb.io.formats.PixelFormat` that holds them all, and the frames
as stored, an unreadable one reported and skipped."""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps

from d2turb.errors import D2TurbError
from d2turb.io.formats import PixelFormat, image_format
from d2turb.io.jobs import named_error
from d2turb.io.read import list_images, read_stored


class FrameFolder:
    """The frames of ``folder`` (:func:`~d2turb.io.read.list_images`: sorted, hidden files skipped): iterated,
    (stem, frame as stored: :func:`~d2turb.io.read.read_stored`) of each readable one; ``errors.record`` gets each
    unreadable one (named), which is skipped.

    Raises:
        D2TurbError: no images in the folder; frames of different sizes (:func:`check_frame_sizes`).
    """

    def __init__(self, folder: str | os.PathLike, errors):
        self.folder, self.errors = Path(folder), errors
        self.files = list_images(self.folder)
        if not self.files:
            raise D2TurbError(f"{self.folder}: no images in the folder")
        check_frame_sizes(self.folder, self.files)
        self.fmt = _joined(f for f in map(image_format, self.files) if f is not None)

    def __iter__(self) -> Iterator[tuple[str, np.ndarray]]:
        for f in self.files:
            try:
                frame = read_stored(f)
            except D2TurbError as exc:
                self.errors.record(named_error(f, exc))
                continue
            yield f.stem, frame


def _joined(formats) -> PixelFormat:
    """Grey only if every frame is, 16 bits if any frame is (the default where no header could be read)."""
    fmt = None
    for found in formats:
        fmt = found if fmt is None else fmt.joined(found)
    return fmt or PixelFormat()


def _header_size(path: Path) -> tuple[int, int] | None:
    """(width, height) of an image as read_image will give it (EXIF rotation applied), from its header only;
    None when the header cannot be read (the reading pass reports the file)."""
    try:
        with Image.open(path) as im:
            width, height = im.size
            if im.format == "PNG" and "exif" not in im.info and _png_tail_is_plain(path):
                exif = Image.Image.getexif(im)  # what PNG's getexif finds after a full decode that adds nothing
            else:
                exif = im.getexif()  # a PNG's decodes the image to reach chunks after its pixels (45 ms at 1080p)
            if exif.get(ImageOps.ExifTags.Base.Orientation) in (5, 6, 7, 8):
                width, height = height, width
            return width, height
    except Exception:  # noqa: BLE001 - any unreadable header: left to read_image, which reports it in one line
        return None


def _png_tail_is_plain(path: Path) -> bool:
    """Whether a PNG's chunks after its first IDAT are IDAT and IEND only (walked by their lengths, nothing
    decoded): then the chunks read at open hold all of its metadata (EXIF, text, XMP)."""
    with open(path, "rb") as f:
        if f.read(8) != b"\x89PNG\r\n\x1a\n":
            return False
        seen_idat = False
        while len(head := f.read(8)) == 8:
            length, kind = struct.unpack(">I4s", head)
            if kind == b"IEND":
                return seen_idat
            if kind == b"IDAT":
                seen_idat = True
            elif seen_idat:
                return False
            f.seek(length + 4, os.SEEK_CUR)  # the data and its CRC
    return False  # cut short


def check_frame_sizes(src: Path, files: list[Path]) -> None:
    """A folder clip's frames must have one size: checked from the headers before anything is measured or written,
    so that a mismatch is one error line and leaves nothing behind."""
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
