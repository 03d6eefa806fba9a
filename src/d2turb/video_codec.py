"""A clip through a video codec and back, in memory (:func:`encode_decode`): what a camera or a video file leaves
of it, for the field-realistic clips (``d2turb.data.field``). Reading and writing video files: :mod:`d2turb.video`."""

from __future__ import annotations

from fractions import Fraction

import numpy as np

from d2turb.errors import D2TurbError
from d2turb.video import VIDEO_HINT, X264_PRESET

VIDEO_CODECS = {"h264": "libx264", "h265": "libx265"}
MIN_CODEC_SIDE = 64  # encode_decode pads smaller frames to this (x265's largest coding unit)


def encode_decode(frames: np.ndarray, codec: str, bitrate_bps: int, fps: float = 30.0) -> np.ndarray:
    """A clip through a video codec and back, in memory (PyAV): what a camera or a video file leaves of it.

    Single-threaded, and x264 without its assembly (which read memory it had not written: 198² clips came out
    different from one encoding to the next; C only costs about 0.3 s per 32 frames of 256²), so that the result
    depends on the input and settings alone (tests/test_camera.py); average-bitrate
    rate control at ``bitrate_bps``, yuv420p (odd sizes padded by one edge row/column, cropped after), x264/x265
    speed preset ``X264_PRESET``, one keyframe at the start (GOP = the clip). Frames under ``MIN_CODEC_SIDE`` px a
    side are padded (edge) to it: libx265 corrupted the heap on 36² frames after larger ones in one process.

    Args:
        frames: (N, H, W, 3) uint8 RGB frames.
        codec: ``"h264"`` (libx264) or ``"h265"`` (libx265).
        bitrate_bps: target bitrate in bits per second.
        fps: frame rate of the stream (with the bitrate, sets the bits per frame).
    Returns:
        (N, H, W, 3) uint8, the decoded frames.
    Raises:
        D2TurbError: PyAV missing, an unknown codec, or a stream that does not decode to N frames.
    """
    import io

    try:
        import av
    except ImportError as exc:
        raise D2TurbError(f"encoding video needs PyAV; {VIDEO_HINT}") from exc
    if codec not in VIDEO_CODECS:
        raise D2TurbError(f"codec must be one of {', '.join(VIDEO_CODECS)}, got {codec!r}")
    frames = np.asarray(frames, dtype=np.uint8)
    n, h, w = frames.shape[:3]
    ph, pw = max(h + h % 2, MIN_CODEC_SIDE), max(w + w % 2, MIN_CODEC_SIDE)  # the size the encoder sees
    buf = io.BytesIO()
    with av.open(buf, "w", format="mp4") as container:
        stream = container.add_stream(VIDEO_CODECS[codec], rate=Fraction(fps).limit_denominator(65535))
        stream.pix_fmt = "yuv420p"
        stream.height, stream.width = ph, pw
        stream.bit_rate = int(bitrate_bps)
        stream.gop_size = max(n, 1)
        stream.codec_context.thread_count = 1
        stream.codec_context.thread_type = "NONE"
        if codec == "h264":  # x264's assembly gave 2-5 different streams in 8 encodings of one 198² clip: C only
            stream.options = {"preset": X264_PRESET, "x264-params": "threads=1:lookahead-threads=1:no-asm=1"}
        else:
            stream.options = {"preset": X264_PRESET, "x265-params": "pools=1:frame-threads=1:log-level=error"}
        for i, frame in enumerate(frames):
            padded = np.ascontiguousarray(np.pad(frame, ((0, ph - h), (0, pw - w), (0, 0)), mode="edge"))
            yuv = av.VideoFrame.from_ndarray(padded, "rgb24").reformat(format="yuv420p", threads=1)
            yuv.pts = i
            for packet in stream.encode(yuv):
                container.mux(packet)
        for packet in stream.encode(None):
            container.mux(packet)
    buf.seek(0)
    out = []
    with av.open(buf, "r") as container:
        container.streams.video[0].thread_type = "NONE"
        for frame in container.decode(video=0):
            out.append(frame.to_ndarray(format="rgb24")[:h, :w])
    if len(out) != n:
        raise D2TurbError(f"the {codec} round trip gave {len(out)} frames, not {n}")
    return np.stack(out)
