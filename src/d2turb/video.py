"""Video files in and out (the ``video`` extra: imageio + PyAV): decoded frames as tensors, the frame rate, and an
mp4 writer that streams frames into a temporary file renamed into place when it is closed.

Frames (3,H,W) float32 in [0, 1]; the command line and the page both read and write videos through here."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from d2turb.errors import D2TurbError
from d2turb.io import atomic_path, to_uint8

VIDEO_SUFFIXES = {".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".gif"}
VIDEO_HINT = "install the video extra: pip install 'd2turb[video]' (from a checkout: pip install -e '.[video]')"
DEFAULT_FPS = 30.0  # when a container does not say


def is_video(path: str | os.PathLike) -> bool:
    path = Path(path)
    return path.suffix.lower() in VIDEO_SUFFIXES and path.is_file()


def _plugin(path: Path) -> str:
    return "pillow" if path.suffix.lower() == ".gif" else "pyav"


def _imageio(path: Path):
    try:
        import imageio.v3 as iio
    except ImportError as exc:
        raise D2TurbError(f"{path}: reading video needs imageio; {VIDEO_HINT}") from exc
    return iio


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [exc.__class__.__name__])[0]


def frame_to_tensor(frame) -> torch.Tensor:
    """A decoded video frame (H,W), (H,W,1|3|4) uint8/uint16/float array → (3,H,W) float32 in [0,1]."""
    arr = np.asarray(frame)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3 or arr.shape[2] not in (1, 3, 4):
        raise D2TurbError(f"unsupported video frame shape {arr.shape}")
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(arr.dtype, 1.0)
    arr = arr[..., :3].astype(np.float32) / scale  # alpha dropped
    if arr.shape[2] == 1:
        arr = arr.repeat(3, axis=2)
    return torch.from_numpy(np.clip(arr, 0, 1)).permute(2, 0, 1).contiguous()


def iter_video(path: str | os.PathLike) -> Iterator[tuple[int, torch.Tensor]]:
    """Yield (index, (3,H,W) float32 frame) for each frame of a video file, decoded one at a time.

    Raises:
        D2TurbError: imageio/PyAV missing, or the file cannot be decoded (one line naming the file).
    """
    path = Path(path)
    iio = _imageio(path)
    try:
        for i, frame in enumerate(iio.imiter(path, plugin=_plugin(path))):
            yield i, frame_to_tensor(frame)
    except (OSError, ValueError, RuntimeError, ImportError) as exc:
        raise D2TurbError(f"{path}: cannot read video ({_first_line(exc)}); {VIDEO_HINT}") from exc


def video_size(path: str | os.PathLike) -> tuple[int, int, int]:
    """(frames, width, height) of a video from its container, without decoding it; frames is 0 where the container
    does not store it (mkv, webm: count by decoding).

    Raises:
        D2TurbError: imageio/PyAV missing, or the file cannot be read (one line naming the file).
    """
    path = Path(path)
    iio = _imageio(path)
    try:
        props = iio.improps(path, plugin=_plugin(path))
    except Exception as exc:  # noqa: BLE001 - any decoder failure means "cannot read this video"
        raise D2TurbError(f"{path}: cannot read video ({_first_line(exc)}); {VIDEO_HINT}") from exc
    frames = int(props.n_images) if props.is_batch else 1
    dims = props.shape[1:3] if props.is_batch else props.shape[0:2]
    return frames, int(dims[1]), int(dims[0])


def video_fps(path: str | os.PathLike) -> float:
    """Frames per second stored in the container (``DEFAULT_FPS`` when it holds none)."""
    path = Path(path)
    iio = _imageio(path)
    try:
        meta = iio.immeta(path, plugin=_plugin(path))
    except Exception as exc:  # noqa: BLE001 - any decoder failure means "cannot read this video"
        raise D2TurbError(f"{path}: cannot read video ({_first_line(exc)}); {VIDEO_HINT}") from exc
    fps = meta.get("fps")
    if fps is None and meta.get("duration"):  # GIF: duration per frame in ms
        fps = 1000.0 / float(meta["duration"])
    try:
        fps = float(fps)
    except (TypeError, ValueError):
        return DEFAULT_FPS
    return fps if np.isfinite(fps) and fps > 0 else DEFAULT_FPS


def can_write_mp4() -> bool:
    """True when the video extra (imageio + PyAV) is installed."""
    try:
        import av  # noqa: F401
        import imageio.v3  # noqa: F401
    except ImportError:
        return False
    return True


class Mp4Writer:
    """Streams frames into an H.264 mp4 (yuv420p: odd sizes are padded by one edge row/column).

    The file is written under a temporary name and renamed onto ``path`` by :meth:`close`; :meth:`abort` (or an
    exception inside ``with``) leaves no file. Frames: (3,H,W) float tensors in [0,1] or (H,W,3) uint8 arrays.
    """

    def __init__(self, path: str | os.PathLike, fps: float):
        try:
            import imageio.v3 as iio
        except ImportError as exc:
            raise D2TurbError(f"{path}: writing video needs imageio; {VIDEO_HINT}") from exc
        self.path = Path(path)
        self._stack = contextlib.ExitStack()
        tmp = self._stack.enter_context(atomic_path(self.path))
        try:
            self._file = iio.imopen(tmp, "w", plugin="pyav", extension=".mp4")
            self._file.init_video_stream("libx264", fps=fps)
        except Exception as exc:  # noqa: BLE001 - e.g. a PyAV without libx264: one line, no temp file left
            self._stack.__exit__(type(exc), exc, exc.__traceback__)
            raise D2TurbError(f"cannot write {self.path}: {_first_line(exc)} ({VIDEO_HINT})") from exc
        self.frames = 0

    def write(self, frame) -> None:
        arr = to_uint8(frame) if isinstance(frame, torch.Tensor) else np.asarray(frame)
        h, w = arr.shape[:2]
        self._file.write_frame(np.pad(arr, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge"))
        self.frames += 1

    def close(self) -> None:
        """Finish the stream and rename the file into place."""
        try:
            self._file.close()
        except Exception as exc:  # noqa: BLE001 - an encoder that fails to flush: one line, no temp file left
            self._stack.__exit__(type(exc), exc, exc.__traceback__)
            raise D2TurbError(f"cannot write {self.path}: {_first_line(exc)}") from exc
        self._stack.close()

    def abort(self) -> None:
        """Drop the file (nothing is left at ``path`` or under a temporary name)."""
        with contextlib.suppress(Exception):
            self._file.close()
        self._stack.__exit__(D2TurbError, D2TurbError("aborted"), None)

    def __enter__(self):
        return self

    def __exit__(self, kind, exc, tb):
        if kind is None:
            self.close()
        else:
            self.abort()
        return False
