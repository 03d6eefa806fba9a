"""The shortcuts of the clip room's whole-frame shifts and checks give what the plain calls give, to the bit:
OutputPose.apply against cv2.remap on full maps, the shift helpers against remap of a constant flow, the ringing
index's kept local range against one made afresh, and a folder's header sizes against PIL's full decode."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest
import torch
from PIL import Image, ImageOps

from d2turb.clip.blur import ringing_index
from d2turb.clip.camera import OutputPose
from d2turb.clip.registration import pixel_grid, remap, shift_flow, shift_maps, shifted
from d2turb.io.folder import _header_size

# shifts off and on OpenCV's half 1/32-px steps (3 + 1/64), small and large, both signs
SHIFTS = [(3.37, -12.61), (3.015625, 1.984375), (-0.5, 0.25), (-40.3, 55.7), (0.0, 0.3), (17.0, -2.0)]


def _apply_oracle(pose: OutputPose, fused, share, flow):
    """OutputPose.apply as first written: every image through cv2.remap on the full (H,W,2) maps."""
    h, w = share.shape
    x0, y0, x1, y1 = pose.common
    xs, ys = np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32)

    def ramp(inside, edge):
        return inside + 1 if edge else np.full_like(inside, np.inf)

    if (x0, y0, x1, y1) != (0, 0, w - 1, h - 1):
        wx = np.clip(np.minimum(ramp(xs - x0, x0 > 0), ramp(x1 - xs, x1 < w - 1)) / 8.0, 0, 1)
        wy = np.clip(np.minimum(ramp(ys - y0, y0 > 0), ramp(y1 - ys, y1 < h - 1)) / 8.0, 0, 1)
        share = 1 - (1 - share) * (wy[:, None] * wx[None, :])
    dx, dy = pose.shift
    maps = shift_flow((h, w), -dx, -dy)
    maps += pixel_grid((h, w))
    out = cv2.remap(fused, maps, None, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE).reshape(fused.shape)
    out_share = cv2.remap(share, maps, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=1.0)
    out_flow = cv2.remap(flow, maps, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    out_flow -= np.array([dx, dy], dtype=np.float32)
    out_flow[out_share >= 1.0] = (pose.frame_shift[0] - dx, pose.frame_shift[1] - dy)
    return out, out_share, out_flow


@pytest.mark.parametrize("channels", [3, 1])
@pytest.mark.parametrize("shift", SHIFTS)
def test_output_pose_apply_equals_remap_on_full_maps(shift, channels):
    rng = np.random.default_rng(len(SHIFTS) * channels)
    h, w = 48, 200
    fused = rng.random((h, w, channels), dtype=np.float32)
    share = np.where(rng.random((h, w)) < 0.1, rng.random((h, w)), 0).astype(np.float32)
    flow = (rng.standard_normal((h, w, 2)) * 3).astype(np.float32)
    pose = OutputPose(shift, (5, 3, w - 8, h - 1), (shift[0] + 1.5, shift[1] - 0.7))
    got = pose.apply(fused.copy(), share.copy(), flow.copy())
    want = _apply_oracle(pose, fused.copy(), share.copy(), flow.copy())
    for g, e in zip(got, want):
        assert g.dtype == e.dtype and g.shape == e.shape
        assert np.array_equal(g, e)


@pytest.mark.parametrize("shift", SHIFTS)
def test_shift_helpers_equal_remap_of_a_constant_flow(shift):
    rng = np.random.default_rng(1)
    gray = (rng.random((40, 70)) * 255).astype(np.uint8)
    rgb = rng.random((40, 70, 3), dtype=np.float32)
    assert np.array_equal(shift_maps((40, 70), *shift), pixel_grid((40, 70)) + shift_flow((40, 70), *shift))
    for image in (gray, gray[..., None], rgb):
        want = remap(image, shift_flow(image.shape[:2], *shift), consume=True)
        got = shifted(image, *shift)
        assert got.shape == want.shape and np.array_equal(got, want)


def test_ringing_index_keeps_the_local_range_only_while_the_frame_is_unchanged():
    g = torch.Generator().manual_seed(0)
    fused = torch.rand(3, 40, 60, generator=g)
    outs = [fused + 0.1 * torch.randn(3, 40, 60, generator=g) for _ in range(3)]

    def fresh(a, b, radius=2):
        a = a.numpy().transpose(1, 2, 0).copy()
        b = b.numpy().transpose(1, 2, 0)
        k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
        over = b - np.clip(b, cv2.erode(a, k), cv2.dilate(a, k))
        return float(np.sqrt(np.mean(over**2))) / float(np.sqrt(np.mean((b - a) ** 2)))

    assert [ringing_index(fused, o) for o in outs] == [fresh(fused, o) for o in outs]
    fused.mul_(0.5)  # changed in place: its range is made again
    assert [ringing_index(fused, o) for o in outs] == [fresh(fused, o) for o in outs]
    assert ringing_index(fused, outs[0], radius=1) == fresh(fused, outs[0], radius=1)


def _chunks(data: bytes) -> list[bytes]:
    out, i = [], 8
    while i < len(data):
        (n,) = struct.unpack(">I", data[i : i + 4])
        out.append(data[i : i + 12 + n])
        i += 12 + n
    return out


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def test_header_sizes_equal_the_decoded_sizes_with_exif_rotation(tmp_path):
    image = Image.fromarray(np.random.default_rng(2).integers(0, 255, (30, 50, 3), dtype=np.uint8))
    exif = Image.Exif()
    exif[ImageOps.ExifTags.Base.Orientation] = 6
    image.save(tmp_path / "plain.png")
    image.save(tmp_path / "exif_before.png", exif=exif)
    chunks = _chunks((tmp_path / "exif_before.png").read_bytes())
    ex = [c for c in chunks if c[4:8] == b"eXIf"]
    rest = [c for c in chunks if c[4:8] != b"eXIf"]
    head = (tmp_path / "plain.png").read_bytes()[:8]
    (tmp_path / "exif_after.png").write_bytes(head + b"".join(rest[:-1] + ex + rest[-1:]))  # after the pixels
    xmp = b"XML:com.adobe.xmp\x00\x00\x00\x00\x00" + b'<x:xmpmeta><rdf:Description tiff:Orientation="8"/></x:xmpmeta>'
    plain = _chunks((tmp_path / "plain.png").read_bytes())
    (tmp_path / "xmp_after.png").write_bytes(head + b"".join(plain[:-1] + [_chunk(b"iTXt", xmp)] + plain[-1:]))
    (tmp_path / "cut.png").write_bytes((tmp_path / "plain.png").read_bytes()[:60])
    image.save(tmp_path / "exif.jpg", exif=exif)
    for name in ("plain.png", "exif_before.png", "exif_after.png", "xmp_after.png", "exif.jpg"):
        with Image.open(tmp_path / name) as im:
            want = ImageOps.exif_transpose(im).size  # decoded and turned
        assert _header_size(tmp_path / name) == want, name
    assert _header_size(tmp_path / "exif_after.png") == (30, 50)
    assert _header_size(tmp_path / "cut.png") is None
