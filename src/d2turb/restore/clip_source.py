"""A clip's frames as ``d2turb restore --temporal`` and ``evaluate --real-clips`` read them: a video file or a folder
of frames, an unreadable frame reported and skipped, the frames' sizes checked from their headers first."""

from __future__ import annotations

from pathlib import Path

from PIL import Image, ImageOps

from d2turb.errors import D2TurbError
from d2turb.io import list_images, read_frame, read_image
from d2turb.io import named_error as _named  # an input's error, naming it
from d2turb.video import is_video, iter_video


def clip_frames(src: Path, errors, as_stored: bool = False) -> tuple[list[str], object]:
    """(frame names, iterator of (3,H,W) frames) of a clip; an unreadable frame of a folder is reported and
    skipped, a video that stops decoding ends the clip there (reported) through ``errors.record``. ``as_stored``:
    a folder's 8-bit frames as (H,W,3) uint8 arrays (:func:`~d2turb.io.read_frame`; ClipRestorer takes both)."""
    names: list[str] = []
    if is_video(src):

        def decoded():
            try:
                for i, frame in iter_video(src):
                    names.append(f"{src.stem}_{i:06d}")
                    yield frame
            except D2TurbError as exc:
                errors.record(_named(src, exc))

        return names, decoded()
    if not src.is_dir():
        raise D2TurbError(f"{src}: a clip is a video file or a folder of frames")
    files = list_images(src)
    if not files:
        raise D2TurbError(f"{src}: no images in the folder")

    def read():
        for f in files:
            try:
                frame = read_frame(f) if as_stored else read_image(f)
            except D2TurbError as exc:
                errors.record(_named(f, exc))
                continue
            names.append(f.stem)
            yield frame

    return names, read()


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
