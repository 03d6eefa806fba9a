"""SER videos, the capture format of planetary, lunar and solar imagers (FireCapture, SharpCap, Genika, PIPP, Siril).

No maintained Python package reads them (PyPI has none; the readers found are inside GPL applications or one-off
scripts), and the format is small, so it is read here, after the SER format description v3 (Grischa Hahn, 2014):
a 178-byte header of little-endian fields, then ``FrameCount`` raw frames, then optionally one 64-bit timestamp
per frame (100-ns ticks):

====== ===================== =========================================================================
offset field                 meaning
====== ===================== =========================================================================
0      FileID (14 bytes)     ``LUCAM-RECORDER``
14     LuID (int32)          camera series (unused)
18     ColorID (int32)       0 mono; 8-11 Bayer RGGB, GRBG, GBRG, BGGR; 16-19 CYYM..; 100 RGB; 101 BGR
22     LittleEndian (int32)  byte order of 16-bit samples (see below)
26     ImageWidth (int32)    px
30     ImageHeight (int32)   px
34     PixelDepthPerPlane    bits a sample, 1-16 (9-16: two bytes a sample)
38     FrameCount (int32)    frames
42     Observer, Instrument, Telescope (40 bytes each), DateTime, DateTime_UTC (int64 each)
====== ===================== =========================================================================

The byte-order flag: the description says 1 = little-endian, but the capture programs write 0 for their
little-endian data and the readers (Siril, SER Player) read it so; here 0 is little-endian, 1 big-endian, except where
the samples settle it: with fewer than 16 bits a sample, the order in which every sample of the first frame fits in
``PixelDepthPerPlane`` bits is used. Samples of 9-15 bits are shifted to the top of 16 bits (a 12-bit 4095 reads
65520); Bayer frames are demosaiced by OpenCV (bilinear) into RGB."""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from d2turb.errors import D2TurbError

HEADER_BYTES = 178
FILE_ID = b"LUCAM-RECORDER"
_BAYER = {8: "RGGB", 9: "GRBG", 10: "GBRG", 11: "BGGR"}
_COLOUR_NAMES = {0: "mono", **{k: f"Bayer {v}" for k, v in _BAYER.items()}, 100: "RGB", 101: "BGR"}
_TICKS_PER_S = 10_000_000


@dataclass(frozen=True)
class SerHeader:
    """The fields of a SER header that decoding needs (``frames``: those the file holds, ``fps``: from the
    timestamps, None without them)."""

    color_id: int
    width: int
    height: int
    depth: int
    frames: int
    little_endian_flag: int
    fps: float | None = None

    @property
    def planes(self) -> int:
        return 3 if self.color_id in (100, 101) else 1

    @property
    def sample_bytes(self) -> int:
        return 1 if self.depth <= 8 else 2

    @property
    def frame_bytes(self) -> int:
        return self.width * self.height * self.planes * self.sample_bytes

    @property
    def channels(self) -> int:
        """Channels of the decoded frames: 1 (mono) or 3 (RGB, BGR, Bayer demosaiced)."""
        return 1 if self.color_id == 0 else 3


def read_ser_header(path: str | os.PathLike) -> SerHeader:
    """The header of a SER file, checked against the file's size.

    Raises:
        D2TurbError: not a SER file, a colour layout not read here (CYYM..), a depth over 16 bits, or no frame.
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(HEADER_BYTES)
            size = os.fstat(f.fileno()).st_size
    except OSError as exc:
        raise D2TurbError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    if len(head) < HEADER_BYTES or not head.startswith(FILE_ID):
        raise D2TurbError(f"{path}: not a SER file (no LUCAM-RECORDER header)")
    _lu, color_id, flag, width, height, depth, count = struct.unpack_from("<7i", head, 14)
    if color_id not in _COLOUR_NAMES:
        raise D2TurbError(
            f"{path}: SER colour layout {color_id} is not read (mono, Bayer RGGB/GRBG/GBRG/BGGR, RGB, BGR)"
        )
    if not 1 <= depth <= 16 or width < 2 or height < 2:
        raise D2TurbError(f"{path}: SER header gives {width}x{height} px of {depth} bits: not a readable SER file")
    header = SerHeader(color_id, width, height, depth, max(count, 0), flag)
    held = (size - HEADER_BYTES) // header.frame_bytes
    frames = min(count, held) if count > 0 else held  # a capture not closed properly may say 0
    if frames < 1:
        raise D2TurbError(f"{path}: SER file holds no whole frame")
    fps = None
    if count > 1 and size >= HEADER_BYTES + count * header.frame_bytes + 8 * count:
        with open(path, "rb") as f:
            f.seek(HEADER_BYTES + count * header.frame_bytes)
            first, *_, last = struct.unpack(f"<{count}q", f.read(8 * count))
        if last > first:
            fps = (count - 1) * _TICKS_PER_S / (last - first)
    return SerHeader(color_id, width, height, depth, frames, flag, fps)


def _byte_order(header: SerHeader, first: bytes) -> str:
    if header.sample_bytes == 1:
        return "<"
    if header.depth < 16:
        limit = 1 << header.depth
        fits = [o for o in "<>" if int(np.frombuffer(first, f"{o}u2").max()) < limit]
        if len(fits) == 1:
            return fits[0]
    return "<" if header.little_endian_flag == 0 else ">"


def _demosaic(raw: np.ndarray, pattern: str) -> np.ndarray:
    import cv2

    code = getattr(cv2, f"COLOR_Bayer{pattern}2RGB", None)
    if code is None:  # OpenCV 4 names a pattern by its second row's second and third samples
        old = {"RGGB": "BG", "GRBG": "GB", "GBRG": "GR", "BGGR": "RG"}[pattern]
        code = getattr(cv2, f"COLOR_Bayer{old}2RGB")
    return cv2.cvtColor(raw, code)


def iter_ser(path: str | os.PathLike, header: SerHeader | None = None) -> Iterator[np.ndarray]:
    """The frames of a SER file, one at a time: (H,W) mono or (H,W,3) RGB, uint8 (depth <= 8) or uint16.

    Raises:
        D2TurbError: as :func:`read_ser_header`; a file that ends inside a frame after those yielded.
    """
    path = Path(path)
    header = header or read_ser_header(path)
    h, w, n = header.height, header.width, header.frame_bytes
    order = None
    with open(path, "rb") as f:
        f.seek(HEADER_BYTES)
        for _ in range(header.frames):
            data = f.read(n)
            if len(data) < n:
                raise D2TurbError(f"{path}: SER file ends inside a frame")
            if order is None:
                order = _byte_order(header, data)
            if header.sample_bytes == 1:
                frame = np.frombuffer(data, np.uint8)
            else:
                frame = np.frombuffer(data, f"{order}u2").astype(np.uint16)
                if header.depth < 16:
                    frame = frame << np.uint16(16 - header.depth)
            frame = frame.reshape((h, w, 3) if header.planes == 3 else (h, w))
            if header.color_id == 101:
                frame = frame[..., ::-1]
            elif header.color_id in _BAYER:
                frame = _demosaic(np.ascontiguousarray(frame), _BAYER[header.color_id])
            yield np.ascontiguousarray(frame)
