"""Video files in and out (the ``video`` extra: imageio + PyAV): decoded frames as tensors, the frame rate, and an
mp4 writer that streams frames into a temporary file renamed into place when it is closed.

Frames (3,H,W) float32 in [0, 1]; the command line and the page both read and write videos through here."""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import os
import re
import signal
import stat
import threading
from collections.abc import Iterator
from fractions import Fraction
from pathlib import Path

import numpy as np
import torch

from d2turb.errors import D2TurbError
from d2turb.io import SharedUint8, atomic_path, to_uint8

VIDEO_SUFFIXES = {".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".gif", ".y4m"}
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


_GREY_PIX_FMTS = ("gray", "ya", "y400", "monow", "monob")


def _pix_format(stream) -> tuple[int, int]:
    """(channels, bits) of a decoded video stream's pixels: 1 for grey formats, 16 for more than 8 bits a sample."""
    name = stream.codec_context.pix_fmt or ""
    try:
        import av

        depth = max(c.bits for c in av.VideoFormat(name).components) if name else 8
    except Exception:  # noqa: BLE001 - a format PyAV does not describe: 8 bits
        depth = 8
    return (1 if name.startswith(_GREY_PIX_FMTS) else 3), (16 if depth > 8 else 8)


_SIGINT = threading.Event()


@contextlib.contextmanager
def sigint_noted():
    """Within: Ctrl-C (SIGINT) also sets a flag that :class:`VideoSource` checks after each frame and at the stream's
    end. A SIGINT that came while PyAV waited for a pipe's data was lost (measured: the run went on to the end of the
    stream and exited 0); the flag makes it stop at the next frame instead. Main thread only (elsewhere a no-op)."""
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or previous == signal.SIG_IGN:
        yield
        return

    def noted(signum, frame):
        _SIGINT.set()
        if callable(previous):
            previous(signum, frame)  # Python's default handler raises KeyboardInterrupt
        raise KeyboardInterrupt

    _SIGINT.clear()
    signal.signal(signal.SIGINT, noted)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        _SIGINT.clear()


class VideoSource:
    """A video decoded by PyAV with its pixels as stored: (H,W) grey or (H,W,3) RGB, uint8, or uint16 where the
    stream holds more than 8 bits a sample. ``source``: a file, or anything FFmpeg opens (``-`` for standard input,
    a URL, a capture device); ``channels``, ``bits``, ``fps`` and ``frames`` (0 where the container does not say)
    are known once it is open.

    Raises:
        D2TurbError: PyAV missing, or the source cannot be opened (one line naming it).
    """

    def __init__(self, source: str | os.PathLike, options: dict | None = None, input_format: str | None = None):
        try:
            import av
        except ImportError as exc:
            raise D2TurbError(f"{source}: reading video needs PyAV; {VIDEO_HINT}") from exc
        self.source = str(source)
        target = "pipe:0" if self.source == "-" else self.source  # FFmpeg's pipe: frames as they come, not in blocks
        if input_format is None and self.source.startswith("/dev/video"):
            input_format = "video4linux2"
        try:
            self._container = av.open(target, "r", format=input_format, options=options or {})
            self._stream = self._container.streams.video[0]
        except (av.FFmpegError, OSError, IndexError, ValueError) as exc:
            raise D2TurbError(f"{self.source}: cannot open video ({_first_line(exc)})") from exc
        self._stream.thread_type = "AUTO"
        self.channels, self.bits = _pix_format(self._stream)
        rate = self._stream.average_rate or self._stream.guessed_rate
        self.fps = float(rate) if rate else DEFAULT_FPS
        self.frames = int(self._stream.frames or 0)
        self._format = {(1, 8): "gray", (1, 16): "gray16le", (3, 8): "rgb24", (3, 16): "rgb48le"}[
            (self.channels, self.bits)
        ]

    def __iter__(self) -> Iterator[np.ndarray]:
        """The frames in order, decoded one at a time; a stream that stops decoding raises D2TurbError there."""
        try:
            for frame in self._container.decode(self._stream):
                if _SIGINT.is_set():
                    raise KeyboardInterrupt
                yield frame.to_ndarray(format=self._format)
        except Exception as exc:  # noqa: BLE001 - any decoder failure ends the clip there, in one line
            raise D2TurbError(f"{self.source}: cannot read video ({_first_line(exc)})") from exc
        finally:
            self.close()
        if _SIGINT.is_set():
            raise KeyboardInterrupt

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._container.close()


def is_stream(source: str | os.PathLike) -> bool:
    """True for what is read once, as it comes: ``-`` (standard input), a named pipe, a URL (``rtsp://``,
    ``http://``, ``tcp://`` ...: anything FFmpeg opens) or a capture device (``/dev/video0``)."""
    text = os.fspath(source)
    if text == "-" or re.match(r"^[A-Za-z][A-Za-z0-9+.-]*://", text) is not None or text.startswith("/dev/video"):
        return True
    try:
        return stat.S_ISFIFO(os.stat(text).st_mode)  # a named pipe another process writes into
    except OSError:
        return False


def stream_name(source: str | os.PathLike) -> str:
    """NAME of a stream's outputs: ``stdin`` for ``-``, else the last part of its path (``rtsp://cam/live`` →
    ``live``, ``/dev/video0`` → ``video0``), ``stream`` when that is empty."""
    text = os.fspath(source)
    if text == "-":
        return "stdin"
    tail = re.sub(r"^[A-Za-z][A-Za-z0-9+.-]*://[^/]*", "", text).split("?")[0].rstrip("/").rsplit("/", 1)[-1]
    return re.sub(r"[^A-Za-z0-9_.-]", "_", Path(tail).stem) or "stream"


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


# x264's speed preset: "veryfast" encodes 1080p at about half the CPU of the default "medium" with files of the same
# size at the default quality (CRF 23) on the real street clip (benchmarks/RESULTS.md, issue 35)
X264_PRESET = "veryfast"
# Mp4Writer's slice threads, fixed: x264's bytes depend on its thread count, which "auto" takes from the CPUs this
# process may use (2 = auto on the 2-core machine: its 1080p files unchanged)
X264_THREADS = 2
# the CPU features with which x264 runs its AVX-512 code (x264 common/cpu.c: F, CD, DQ, BW and VL)
_X264_AVX512 = ("AVX512F", "AVX512CD", "AVX512DQ", "AVX512BW", "AVX512VL")


def _cpu_features() -> dict:
    try:
        from numpy._core._multiarray_umath import __cpu_features__  # numpy >= 2
    except ImportError:
        try:
            from numpy.core._multiarray_umath import __cpu_features__
        except ImportError:
            return {}
    return dict(__cpu_features__)


def x264_params() -> str:
    """Mp4Writer's ``x264-params``: the same frames give the same file, run after run.

    x264's AVX-512 code reads memory it has not written (its macroblock-tree rate control): the bytes of a 56x48
    clip depended on what the heap held before (``MALLOC_PERTURB_`` 0, 77, 165 and 200 gave four different files of
    the same frames, measured; the page's in-process run and its command line's rerun differed so). Where x264 would
    use AVX-512 its assembly stops at AVX2 (every CPU with x264's AVX-512 set has AVX2, FMA3 and BMI2): the files
    are then the same under every perturbation, and 1080p encodes in no more CPU time (1.45 s against 1.8 s for 20
    frames of the street clip). Elsewhere x264 chooses its own assembly."""
    features = _cpu_features()
    return "asm=AVX2" if all(features.get(name) for name in _X264_AVX512) else ""


class Mp4Writer:
    """Streams frames into an H.264 mp4 (PyAV, libx264 at ``preset``, default ``X264_PRESET``; ``X264_THREADS`` slice
    threads and :func:`x264_params`: the same frames give the same bytes; yuv420p: odd sizes are padded by one edge
    row/column), encoding in a thread of its own (at most two frames wait: the caller computes the next frame while
    the last one is encoded; the encoder releases the GIL).

    The file is written under a temporary name and renamed onto ``path`` by :meth:`close`; :meth:`abort` (or an
    exception inside ``with``) leaves no file. Frames: (3,H,W) float tensors in [0,1], (H,W,3) uint8 arrays, or a
    :class:`~d2turb.io.SharedUint8` of a tensor (converted once for this and another consumer).
    """

    def __init__(self, path: str | os.PathLike, fps: float, preset: str = X264_PRESET):
        try:
            import av
        except ImportError as exc:
            raise D2TurbError(f"{path}: writing video needs PyAV; {VIDEO_HINT}") from exc
        self.path = Path(path)
        self._stack = contextlib.ExitStack()
        tmp = self._stack.enter_context(atomic_path(self.path))
        try:
            self._container = av.open(str(tmp), "w", format="mp4")
            self._stream = self._container.add_stream("libx264", rate=Fraction(fps).limit_denominator(65535))
            self._stream.pix_fmt = "yuv420p"
            self._stream.codec_context.thread_type = "SLICE"
            self._stream.codec_context.thread_count = X264_THREADS
            params = x264_params()
            self._stream.options = {"preset": preset, **({"x264-params": params} if params else {})}
        except Exception as exc:  # noqa: BLE001 - e.g. a PyAV without libx264: one line, no temp file left
            self._stack.__exit__(type(exc), exc, exc.__traceback__)
            raise D2TurbError(f"cannot write {self.path}: {_first_line(exc)} ({VIDEO_HINT})") from exc
        self._av = av
        self._pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="d2turb-mp4")
        self._pending: collections.deque = collections.deque()
        self.frames = 0

    def _encode(self, frame, index: int | None = None) -> None:
        yuv = None
        if frame is not None:  # to the encoder's yuv420p here, on one thread: swscale's threads vary the output
            yuv = self._av.VideoFrame.from_ndarray(self._padded(frame), "rgb24").reformat(format="yuv420p", threads=1)
            yuv.pts = index
        for packet in self._stream.encode(yuv):
            self._container.mux(packet)

    def _wait(self, keep: int) -> None:
        while len(self._pending) > keep:
            self._pending.popleft().result()  # an encoder error is raised here, in the caller

    @staticmethod
    def _padded(frame) -> np.ndarray:
        if isinstance(frame, SharedUint8):
            frame = frame()
        arr = to_uint8(frame) if isinstance(frame, torch.Tensor) else np.asarray(frame, dtype=np.uint8)
        if arr.ndim == 2 or arr.shape[2] == 1:  # grey: the encoder takes RGB
            arr = np.repeat(arr.reshape(arr.shape[0], arr.shape[1], 1), 3, axis=2)
        h, w = arr.shape[:2]
        return np.ascontiguousarray(np.pad(arr, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge"))

    def write(self, frame) -> None:
        """Queue one frame (converted to 8 bits in the encoding thread; the caller must not change it after)."""
        if self.frames == 0:
            if isinstance(frame, torch.Tensor):
                h, w = frame.shape[-2:]
            else:
                h, w = frame.shape[:2] if isinstance(frame, SharedUint8) else np.shape(frame)[:2]
            self._stream.height, self._stream.width = h + h % 2, w + w % 2
        self._wait(1)
        self._pending.append(self._pool.submit(self._encode, frame, self.frames))
        self.frames += 1

    def close(self) -> None:
        """Finish the stream and rename the file into place."""
        try:
            self._wait(0)
            self._encode(None)  # flush the encoder's delayed frames
            self._container.close()
        except Exception as exc:  # noqa: BLE001 - an encoder that fails to flush: one line, no temp file left
            self.abort()
            raise D2TurbError(f"cannot write {self.path}: {_first_line(exc)}") from exc
        finally:
            self._pool.shutdown(wait=True)
        self._stack.close()

    def abort(self) -> None:
        """Drop the file (nothing is left at ``path`` or under a temporary name)."""
        for job in self._pending:
            job.cancel()
        self._pool.shutdown(wait=True)
        with contextlib.suppress(Exception):
            self._container.close()
        self._stack.__exit__(D2TurbError, D2TurbError("aborted"), None)

    def __enter__(self):
        return self

    def __exit__(self, kind, exc, tb):
        if kind is None:
            self.close()
        else:
            self.abort()
        return False


class Y4mWriter:
    """Frames to a YUV4MPEG2 stream (``-``: standard output, for ``| ffplay -`` or ``| ffmpeg -i - ...``) as they
    come: 8-bit RGB as yuv444p (BT.601, limited range: swscale's default), 16-bit RGB as yuv444p16, grey as mono or
    mono16. Frames: (H,W) or (H,W,3) uint8 or uint16 arrays, of the ``channels`` and ``bits`` given."""

    _OUT = {(1, 8): "gray", (1, 16): "gray16le", (3, 8): "yuv444p", (3, 16): "yuv444p16le"}
    _IN = {(1, 8): "gray", (1, 16): "gray16le", (3, 8): "rgb24", (3, 16): "rgb48le"}

    def __init__(self, target: str | os.PathLike, fps: float, channels: int = 3, bits: int = 8):
        try:
            import av
        except ImportError as exc:
            raise D2TurbError(f"writing y4m needs PyAV; {VIDEO_HINT}") from exc
        self._av, self._key = av, (channels, bits)
        name = "pipe:1" if os.fspath(target) == "-" else os.fspath(target)
        self._container = av.open(name, "w", format="yuv4mpegpipe")
        self._stream = self._container.add_stream("rawvideo", rate=Fraction(fps).limit_denominator(65535))
        self._stream.pix_fmt = self._OUT[self._key]
        self.frames = 0

    def write(self, frame: np.ndarray) -> None:
        arr = np.ascontiguousarray(frame)
        if self.frames == 0:
            self._stream.height, self._stream.width = arr.shape[:2]
        video = self._av.VideoFrame.from_ndarray(arr, self._IN[self._key])
        if self._IN[self._key] != self._OUT[self._key]:
            video = video.reformat(format=self._OUT[self._key], threads=1)
        video.pts = self.frames
        for packet in self._stream.encode(video):
            self._container.mux(packet)
        self.frames += 1

    def close(self) -> None:
        with contextlib.suppress(BrokenPipeError):
            for packet in self._stream.encode(None):
                self._container.mux(packet)
            self._container.close()
