from io import BytesIO

import numpy as np
import pytest
import torch
from PIL import Image

from d2turb.errors import D2TurbError
from d2turb.io import read_image, write_image
from d2turb.ops import warp


@pytest.mark.parametrize("mode", ["L", "RGBA", "P", "I;16", "RGB"])
def test_read_image_modes(tmp_path, mode):
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)
    if mode == "I;16":
        img = Image.new("I;16", (30, 20))
        img.frombytes((rgb[..., 0].astype("<u2") * 257).tobytes())
    else:
        img = Image.fromarray(rgb).convert(mode)
    path = tmp_path / "x.png"
    img.save(path)
    x = read_image(path)
    assert x.shape == (3, 20, 30) and x.dtype == torch.float32
    assert 0 <= x.min() and x.max() <= 1
    if mode == "I;16":
        torch.testing.assert_close(x[0], torch.from_numpy(rgb[..., 0] / 255.0).float(), atol=1e-6, rtol=0)
    else:  # the 8-bit values over 255, rounded once from float64 (Pillow's own RGB expansion of L, RGBA, P)
        with Image.open(path) as img:
            expected = (np.asarray(img.convert("RGB"), dtype=np.float64) / 255.0).astype(np.float32)
        assert torch.equal(x, torch.from_numpy(expected.transpose(2, 0, 1).copy()))


@pytest.fixture(params=["imagecodecs", "pillow"])
def png_codec(request, monkeypatch):
    """Each PNG codec of ``d2turb.io``: imagecodecs, or Pillow as on a machine without it."""
    import d2turb.io.png

    if request.param == "pillow":
        monkeypatch.setattr(d2turb.io.png, "imagecodecs", None)
    else:
        pytest.importorskip("imagecodecs")
    return request.param


def _rgb_png_variants(folder, rgb):
    """8-bit RGB PNG files as cameras and editors write them: plain, upper-case suffix, with transparency and
    gamma chunks, and with an orientation in each place Pillow reads one (eXIf, ImageMagick text, XMP)."""
    from PIL import PngImagePlugin

    img = Image.fromarray(rgb)
    exif = Image.Exif()
    exif[0x0112] = 6  # rotate 90 degrees clockwise on display
    text, xmp, gamma = (PngImagePlugin.PngInfo() for _ in range(3))
    raw = b"Exif\0\0" + exif.tobytes(0)
    text.add_text("Raw profile type exif", f"\nexif\n{len(raw):8d}\n{raw.hex()}")
    xmp.add_itxt("XML:com.adobe.xmp", '<x:xmpmeta><rdf:Description tiff:Orientation="6"/></x:xmpmeta>')
    gamma.add(b"gAMA", (45455).to_bytes(4, "big"))
    variants = {
        "plain.png": {},
        "upper.PNG": {},
        "trns.png": {"transparency": tuple(int(v) for v in rgb[0, 0])},
        "gamma.png": {"pnginfo": gamma},
        "exif.png": {"exif": exif},
        "text.png": {"pnginfo": text},
        "xmp.png": {"pnginfo": xmp},
    }
    for name, options in variants.items():
        img.save(folder / name, format="PNG", **options)
    return [folder / name for name in variants]


def test_read_image_of_rgb_png_files_equals_pillows_decoding(tmp_path, png_codec):
    """8-bit RGB PNG takes libpng where it can; the values, and the orientation where one is given, are those of
    Pillow with its EXIF transpose (the oracle)."""
    from PIL import ImageOps

    rgb = np.random.default_rng(1).integers(0, 256, (12, 20, 3), dtype=np.uint8)
    rotated = 0
    for path in _rgb_png_variants(tmp_path, rgb):
        with Image.open(path) as img:
            expected = np.asarray(ImageOps.exif_transpose(img.convert("RGB")), dtype=np.float64) / 255.0
        x = read_image(path)
        assert torch.equal(x, torch.from_numpy(expected.astype(np.float32).transpose(2, 0, 1).copy())), path.name
        rotated += x.shape[1:] == (20, 12)
    assert rotated == 3  # each orientation was found


def test_read_corrupt_image_raises_one_line(tmp_path):
    path = tmp_path / "bad.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    with pytest.raises(D2TurbError, match="bad.png: cannot read image"):
        read_image(path)


def test_exif_orientation_respected(tmp_path):
    img = Image.new("RGB", (40, 20), (255, 0, 0))
    exif = img.getexif()
    exif[0x0112] = 6  # rotate 90 degrees clockwise on display
    img.save(tmp_path / "r.jpg", exif=exif)
    assert read_image(tmp_path / "r.jpg").shape == (3, 40, 20)


def test_write_image_roundtrip_and_no_temp_left(tmp_path):
    x = torch.rand(3, 16, 24)
    write_image(tmp_path / "a.png", x)
    y = read_image(tmp_path / "a.png")
    torch.testing.assert_close(y, x, atol=0.5 / 255 + 1e-6, rtol=0)
    assert [p.name for p in tmp_path.iterdir()] == ["a.png"]


@pytest.mark.parametrize("level", [0, 1, 6, 9])
def test_png_writer_is_lossless_at_every_level(tmp_path, png_codec, level):
    """Decoded by Pillow: the exact 8-bit RGB and grey values and 16-bit depth, with either encoder."""
    from skimage import data

    from d2turb.data.layout import write_depth_png

    rgb = data.astronaut()[100:228, 150:310]
    write_image(tmp_path / "rgb.png", rgb, level)
    write_image(tmp_path / "grey.png", rgb[..., 1], level)
    depth = torch.rand(1, 40, 50, generator=torch.Generator().manual_seed(level))
    write_depth_png(tmp_path / "depth.png", depth, level)
    with Image.open(tmp_path / "rgb.png") as a, Image.open(tmp_path / "grey.png") as b:
        assert (a.mode, b.mode) == ("RGB", "L")
        assert np.array_equal(np.asarray(a), rgb) and np.array_equal(np.asarray(b), rgb[..., 1])
    with Image.open(tmp_path / "depth.png") as d:
        expected = np.round(depth[0].double().numpy() * 65535)
        assert d.mode.startswith("I") and np.array_equal(np.asarray(d).astype(np.float64), expected)


@pytest.mark.parametrize("shape", [(3, 5, 7), (1, 5, 7), (5, 7)])
def test_to_uint8_rounds_to_the_nearest_level_and_clips(shape):
    from d2turb.io import to_uint8

    rng = np.random.default_rng(len(shape))
    levels = rng.integers(0, 256, shape)
    x = (levels + rng.uniform(-0.45, 0.45, shape)) / 255  # nearest level unambiguous
    x[..., 0], x[..., 1] = -0.2, 1.3
    levels[..., 0], levels[..., 1] = 0, 255
    out = to_uint8(torch.from_numpy(x))
    expected = np.moveaxis(levels, 0, -1) if len(shape) == 3 else levels
    expected = expected[..., 0] if expected.ndim == 3 and expected.shape[2] == 1 else expected
    assert out.dtype == np.uint8 and out.flags.c_contiguous and np.array_equal(out, expected)


@pytest.mark.parametrize(
    "shape, dtype",
    [((1, 7), np.uint8), ((5, 1, 3), np.uint8), ((9, 6, 2), np.uint8), ((4, 5, 4), np.uint8), ((6, 3, 3), np.uint16)],
)
def test_png_level1_is_decoded_exactly_by_libpng_and_pillow(shape, dtype):
    """The level-1 encoder assembles the PNG itself (Up filter, libdeflate): one row, one column, grey+alpha,
    RGBA, 16-bit RGB and a strided view decode to the same values with libpng and Pillow (which checks CRCs)."""
    imagecodecs = pytest.importorskip("imagecodecs")
    from d2turb.io import encode_png

    rng = np.random.default_rng(sum(shape))
    array = rng.integers(0, np.iinfo(dtype).max, size=shape, endpoint=True, dtype=dtype)
    if array.ndim == 3:  # the HWC view of a CHW array, as the commands write a tensor
        strided = np.moveaxis(np.ascontiguousarray(np.moveaxis(array, -1, 0)), 0, -1)
    else:
        strided = np.repeat(array, 2, axis=1)[:, ::2]
    assert not strided.flags.c_contiguous
    for view in (array, strided):
        data = encode_png(view, 1)
        assert np.array_equal(imagecodecs.png_decode(data), array)
        with Image.open(BytesIO(data)) as img:
            img.load()
            if dtype == np.uint8:
                assert np.array_equal(np.asarray(img), array)


def test_png_levels_trade_size_and_bad_levels_are_refused(png_codec):
    from skimage import data, filters

    from d2turb.io import encode_png

    # a blurred photograph, like the simulator's outputs (on sharp, noisy ones run-length at level 1 can
    # beat LZ77 at every level)
    rgb = np.round(filters.gaussian(data.astronaut()[:256, :256], sigma=1.5, channel_axis=-1) * 255).astype(np.uint8)
    sizes = [len(encode_png(rgb, level)) for level in (0, 1, 9)]
    assert sizes[0] >= rgb.size and sizes[0] > sizes[1] > sizes[2]  # level 0 stores the filtered rows
    for level in (-1, 10):
        with pytest.raises(D2TurbError, match="PNG level must be 0-9"):
            encode_png(rgb, level)
    for shape in [(0, 5, 3), (4, 0), (4, 5, 5), (2, 3, 4, 5)]:
        with pytest.raises(D2TurbError, match="cannot write an image of shape"):
            encode_png(np.zeros(shape, np.uint8))
    with Image.open(BytesIO(encode_png(rgb[..., :1]))) as single:
        assert single.mode == "L" and np.array_equal(np.asarray(single), rgb[..., 0])


def test_warp_integer_shift_and_gradcheck():
    img = torch.rand(1, 3, 8, 9, dtype=torch.float64)
    flow = torch.zeros(1, 2, 8, 9, dtype=torch.float64)
    flow[:, 0] = 1.0  # sample one pixel to the right
    out = warp(img, flow)
    torch.testing.assert_close(out[..., :-1], img[..., 1:])
    flow = (torch.rand(1, 2, 5, 6, dtype=torch.float64) - 0.5).requires_grad_()
    img = torch.rand(1, 2, 5, 6, dtype=torch.float64, requires_grad=True)
    # keep sample points away from integer positions where bilinear is not differentiable
    flow.data = flow.data * 0.8 + 0.1
    assert torch.autograd.gradcheck(lambda i, f: warp(i, f), (img, flow))


def test_warp_subpixel_shift_of_a_ramp_is_analytic():
    """out(x) = image(x + flow(x)): bilinear sampling reproduces a linear function exactly, so a ramp
    I = a + b·x + c·y warped by any flow (inside the image) is a + b·(x + fx) + c·(y + fy)."""
    h, w = 12, 17
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    img = (0.1 + 0.03 * xs + 0.05 * ys)[None, None]
    g = torch.Generator().manual_seed(0)
    flow = torch.stack([0.7 * torch.ones(h, w), -1.3 * torch.ones(h, w)])[None].double()
    flow = flow + 0.4 * torch.rand(1, 2, h, w, generator=g, dtype=torch.float64)  # non-constant, sub-pixel
    out = warp(img, flow)
    expected = 0.1 + 0.03 * (xs + flow[0, 0]) + 0.05 * (ys + flow[0, 1])
    inside = (xs + flow[0, 0] <= w - 1) & (ys + flow[0, 1] >= 0)
    torch.testing.assert_close(out[0, 0][inside], expected[inside], atol=1e-12, rtol=0)
    # a constant shift of +2.5 px in x moves content left: out(x) = img(x + 2.5)
    out = warp(img, torch.tensor([2.5, 0.0], dtype=torch.float64).view(1, 2, 1, 1).expand(1, 2, h, w))
    torch.testing.assert_close(out[0, 0, :, :-3], img[0, 0, :, 2:-1] + 0.5 * 0.03, atol=1e-12, rtol=0)


def test_check_shape_accepts_matching_shapes_and_names_the_mismatch():
    from d2turb.ops import check_shape

    check_shape(torch.zeros(2, 3, 4, 5), "B C H W")  # names match any size
    check_shape(torch.zeros(1, 2, 4, 5), "B 2 H W", floating=True)  # integers only that size
    check_shape(torch.zeros(3, 1, 40, 56, dtype=torch.uint8), "B 1 40 56")
    check_shape(torch.zeros(3, 4, 5), "[B] 3 H W")  # bracketed leading dims may be absent
    check_shape(torch.zeros(2, 3, 4, 5), "[B] 3 H W")
    cases = [
        (torch.zeros(3, 4, 5), "B C H W", r"^x must have shape \(B, C, H, W\), got \(3, 4, 5\)$"),  # rank
        (torch.zeros(1, 3, 4, 5), "B 2 H W", r"^x must have shape \(B, 2, H, W\), got \(1, 3, 4, 5\)$"),  # size
        (torch.zeros(1, 1, 40, 55), "B 1 40 56", r"^x must have shape \(B, 1, 40, 56\), got \(1, 1, 40, 55\)$"),
        ([[1.0]], "B C H W", r"^x must be a tensor of shape \(B, C, H, W\), got list$"),
        (torch.zeros(4, 5), "[B] 3 H W", r"^x must have shape \(\[B\], 3, H, W\), got \(4, 5\)$"),
        (torch.zeros(1, 2, 3, 4, 5), "[B] 3 H W", r"^x must have shape \(\[B\], 3, H, W\), got \(1, 2, 3, 4, 5\)$"),
        (torch.zeros(1, 4, 5), "[B] 3 H W", r"^x must have shape \(\[B\], 3, H, W\), got \(1, 4, 5\)$"),
    ]
    for x, shape, message in cases:
        with pytest.raises(D2TurbError, match=message):
            check_shape(x, shape, "x")
    with pytest.raises(D2TurbError, match=r"^x must be a floating tensor, got torch.int64$"):
        check_shape(torch.zeros(1, 2, 4, 5, dtype=torch.long), "B 2 H W", "x", floating=True)


def test_a_shared_uint8_converts_once_for_every_thread(tmp_path, monkeypatch):
    """A clip's PNG writer and mp4 encoder share one conversion: the array equals to_uint8's (rounded to nearest,
    clipped), is computed once whatever the number of threads asking, and the PNG written from it is lossless."""
    import threading

    import d2turb.io.png as png

    rng = np.random.default_rng(3)
    image = torch.from_numpy(rng.uniform(-0.1, 1.1, (3, 20, 30)).astype(np.float32))
    calls = []
    real = png.to_uint8
    monkeypatch.setattr(png, "to_uint8", lambda x: calls.append(1) or real(x))
    shared = png.SharedUint8(image)
    assert shared.shape == (20, 30, 3)
    got = []
    threads = [threading.Thread(target=lambda: got.append(shared())) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    expected = np.clip(np.rint(image.numpy() * 255), 0, 255).astype(np.uint8).transpose(1, 2, 0)
    assert len(calls) == 1 and all(a is got[0] for a in got)
    np.testing.assert_array_equal(got[0], expected)
    png.write_image(tmp_path / "a.png", shared)
    np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "a.png")), expected)
