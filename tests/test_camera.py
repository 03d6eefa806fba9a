"""The camera model of the field clips (d2turb.sim.camera, d2turb.video_codec.encode_decode, d2turb.data.field's JPEG),
against independent oracles: IEC 61966-2-1 written from the standard and skimage's sRGB → XYZ, the Poisson–Gaussian
variance formula, skimage's unsharp mask, and sane codec PSNRs."""

import numpy as np
import pytest
import torch

from d2turb.sim.camera import (
    defocus_kernel,
    linear_to_srgb,
    optics_blur,
    poisson_gaussian_noise,
    poisson_gaussian_variance,
    srgb_to_linear,
    unsharp_mask,
)


def _iec_decode(v: np.ndarray) -> np.ndarray:  # IEC 61966-2-1:1999 §5.2, written from the standard
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def _iec_encode(x: np.ndarray) -> np.ndarray:
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def test_srgb_matches_the_standard_and_round_trips_exactly():
    v = np.linspace(0, 1, 100_001)
    lin = srgb_to_linear(torch.from_numpy(v)).numpy()
    np.testing.assert_allclose(lin, _iec_decode(v), rtol=0, atol=1e-15)
    # round trip: exact to float64 rounding, except at the knee where the standard's rounded constants leave a step of
    # 3e-8 (0.04045 / 12.92 = 0.00313080 lies just above 0.0031308, on the power segment)
    back = linear_to_srgb(torch.from_numpy(lin)).numpy()
    np.testing.assert_allclose(back, v, rtol=0, atol=5e-8)
    away = np.abs(v - 0.04045) > 1e-6
    np.testing.assert_allclose(back[away], v[away], rtol=0, atol=1e-12)
    x = np.linspace(0, 1, 100_001)
    np.testing.assert_allclose(linear_to_srgb(torch.from_numpy(x)).numpy(), _iec_encode(x), rtol=0, atol=1e-15)
    # every 8-bit code survives decode → encode in float32
    codes = torch.arange(256, dtype=torch.float32) / 255
    back = torch.round(linear_to_srgb(srgb_to_linear(codes)) * 255)
    assert torch.equal(back, torch.arange(256, dtype=torch.float32))
    # known values of the standard: the segments meet at 0.04045 ↔ 0.0031308; mid grey 0.5 ↔ 0.2140
    assert float(srgb_to_linear(torch.tensor(0.5, dtype=torch.float64))) == pytest.approx(0.21404114, abs=1e-8)


def test_srgb_decode_matches_skimage_xyz():
    skimage_color = pytest.importorskip("skimage.color")
    rgb = np.random.default_rng(0).random((32, 32, 3))
    xyz = skimage_color.rgb2xyz(rgb)  # linearises with the sRGB curve, then the sRGB primaries' matrix
    lin = np.einsum("ij,hwj->hwi", np.linalg.inv(skimage_color.colorconv.xyz_from_rgb), xyz)
    ours = srgb_to_linear(torch.from_numpy(rgb).permute(2, 0, 1)).permute(1, 2, 0).numpy()
    np.testing.assert_allclose(ours, lin, atol=1e-9)


@pytest.mark.parametrize("gain, read", [(1e-3, 2e-3), (1e-4, 5e-4), (2e-3, 0.0)])
def test_poisson_gaussian_variance_follows_the_formula(gain, read):
    levels = torch.tensor([0.01, 0.1, 0.4, 0.9], dtype=torch.float64)
    n = 200_000
    x = levels[:, None].expand(4, n).contiguous()
    y = poisson_gaussian_noise(x, gain, read, torch.Generator().manual_seed(1)).double()
    expected = poisson_gaussian_variance(levels, gain, read)
    var = y.var(1)
    se = expected * np.sqrt(2 / (n - 1))  # standard error of a sample variance (near-Gaussian counts)
    assert torch.all((var - expected).abs() < 5 * se + 1e-12), (var, expected)
    mean_se = (expected / n).sqrt()
    assert torch.all((y.mean(1) - levels).abs() < 5 * mean_se)


def test_unsharp_mask_matches_skimage():
    filters = pytest.importorskip("skimage.filters")
    rng = np.random.default_rng(2)
    img = rng.random((64, 64))
    from scipy import ndimage

    img = ndimage.gaussian_filter(img, 1.0)
    ours = unsharp_mask(torch.from_numpy(img)[None].float(), 0.8, 1.5)[0].numpy()
    ref = filters.unsharp_mask(img, radius=1.5, amount=0.8, preserve_range=True)
    inner = (slice(8, -8), slice(8, -8))  # borders: reflect here, nearest in skimage
    np.testing.assert_allclose(ours[inner], ref[inner], atol=2e-3)
    flat = torch.full((1, 16, 16), 0.3)
    assert torch.allclose(unsharp_mask(flat, 1.0, 1.0), flat, atol=1e-6)


def test_optics_blur_keeps_the_mean_and_the_defocus_disk_has_its_area():
    k = defocus_kernel(3.0)
    assert float(k.sum()) == pytest.approx(1.0, abs=1e-6)
    t = torch.arange(k.shape[0], dtype=torch.float64) - k.shape[0] // 2
    var_x = float((k.double() * t[None, :] ** 2).sum())
    assert var_x == pytest.approx(3.0**2 / 4, rel=0.05)  # a uniform disk of radius r: r²/4 per axis
    img = torch.rand(3, 48, 48, generator=torch.Generator().manual_seed(0))
    out = optics_blur(img, 1.2, 0.6)
    assert out.shape == img.shape
    assert float(out.mean()) == pytest.approx(float(img.mean()), abs=2e-3)
    assert float(out.std()) < float(img.std())


def _natural_clip(frames=12, size=128):
    data = pytest.importorskip("skimage.data")
    base = data.astronaut()[100:400, 150:450]  # a photograph shipped with scikit-image; the camera pans 1 px a frame
    return np.stack([np.ascontiguousarray(base[t : t + size, t : t + size]) for t in range(frames)])


def _psnr(a, b):
    return 10 * np.log10(255**2 / np.mean((a.astype(np.float64) - b) ** 2))


@pytest.mark.parametrize("codec", ["h264", "h265"])
def test_video_codec_round_trip_psnr_is_sane(codec):
    pytest.importorskip("av")
    from d2turb.video_codec import encode_decode

    clip = _natural_clip()
    low = encode_decode(clip, codec, int(0.1 * 128 * 128 * 30))
    high = encode_decode(clip, codec, int(0.6 * 128 * 128 * 30))
    assert low.shape == clip.shape and low.dtype == np.uint8
    p_low, p_high = _psnr(low, clip), _psnr(high, clip)
    assert 24 < p_low < 50 and 24 < p_high < 55, (p_low, p_high)
    assert p_high > p_low


def test_jpeg_round_trip_psnr_is_sane():
    from d2turb.data.field import jpeg_round_trip

    clip = _natural_clip(frames=2)
    p60, p95 = _psnr(jpeg_round_trip(clip, 60), clip), _psnr(jpeg_round_trip(clip, 95), clip)
    assert 28 < p60 < p95 < 55, (p60, p95)


def test_video_codec_takes_small_and_odd_frames():
    pytest.importorskip("av")
    from d2turb.video_codec import encode_decode

    rng = np.random.default_rng(4)
    for h, w in ((128, 128), (36, 36), (29, 31), (44, 36)):  # x265 corrupted the heap on 36² after 128², unpadded
        clip = (rng.random((3, h, w, 3)) * 255).astype(np.uint8)
        for codec in ("h264", "h265"):
            assert encode_decode(clip, codec, int(0.3 * h * w * 30)).shape == clip.shape


@pytest.mark.parametrize("codec", ["h264", "h265"])
def test_video_codec_round_trip_is_repeatable(codec):
    pytest.importorskip("av")
    from d2turb.video_codec import encode_decode

    clip = np.ascontiguousarray(_natural_clip(frames=16, size=198)[..., :190, :])  # sizes off the 16-px grid
    first = encode_decode(clip, codec, int(0.3 * 198 * 190 * 30))
    for _ in range(5):  # x264's assembly gave 2-5 different streams in 8 encodings of such a clip
        assert np.array_equal(encode_decode(clip, codec, int(0.3 * 198 * 190 * 30)), first)
