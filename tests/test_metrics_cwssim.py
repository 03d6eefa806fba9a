"""CW-SSIM (d2turb.eval.cwssim) against independent oracles: its definition (an image against itself is 1), its
point (near-invariant to a 1-px shift that SSIM punishes), its order (monotone in added noise), pyiqa 0.1.16's
CW_SSIM numbers and pyrtools' complex steerable pyramid."""

import numpy as np
import pytest
import torch
from scipy import ndimage
from skimage import data

from d2turb.errors import D2TurbError
from d2turb.eval.cwssim import coarsest_bands, cw_ssim
from d2turb.eval.metrics import ssim

CAMERA = data.camera().astype(np.float64) / 255


def test_an_image_against_itself_is_one():
    rgb = torch.rand(3, 96, 128, generator=torch.Generator().manual_seed(0))
    assert cw_ssim(rgb, rgb) == pytest.approx(1.0, abs=1e-12)
    assert cw_ssim(CAMERA, CAMERA) == pytest.approx(1.0, abs=1e-12)


def test_a_one_pixel_shift_barely_moves_it_while_ssim_drops():
    shifted = np.roll(CAMERA, 1, axis=1)
    t = lambda x: torch.from_numpy(x).float()[None, None]  # noqa: E731
    plain = float(ssim(t(shifted), t(CAMERA)))
    assert cw_ssim(shifted, CAMERA) > 0.995
    assert plain < 0.8  # SSIM loses > 0.2 for the same shift


def test_monotone_in_added_noise():
    noise = np.random.default_rng(2).standard_normal(CAMERA.shape)
    scores = [cw_ssim(np.clip(CAMERA + s * noise, 0, 1), CAMERA) for s in (0.0, 0.02, 0.05, 0.1, 0.2, 0.4)]
    assert all(a > b for a, b in zip(scores, scores[1:])), scores


@pytest.mark.parametrize(
    "case, expected",
    [
        ("transposed", 0.273047),  # pyiqa 0.1.16 CW_SSIM() (level 4, ori 8, K 0, Y channel), float64 input
        ("odd_shift", 0.976926),
        ("astronaut_blur", 0.982053),
    ],
)
def test_agrees_with_pyiqa(case, expected):
    """pyiqa's numbers, computed once with its ssim_arch.CW_SSIM on these images (benchmarks/cwssim_oracle.py). pyiqa
    rounds the luma to whole 8-bit levels, d2turb does not: agreement to 1e-4 in general, to 1e-6 where the luma
    is rounded the same way (below), to 1e-9 where it already is whole levels (the grey camera cases)."""
    if case == "transposed":
        a, b = CAMERA, CAMERA.T.copy()
    elif case == "odd_shift":
        a = CAMERA[100:303, 50:307]
        b = ndimage.shift(a, (2, -3), order=1, mode="nearest")
    else:
        a = data.astronaut().astype(np.float64).transpose(2, 0, 1) / 255
        b = ndimage.gaussian_filter(a, (0, 3, 3))
        a, b = torch.from_numpy(a), torch.from_numpy(b)
    assert cw_ssim(a, b) == pytest.approx(expected, abs=1e-4)


def test_agrees_with_pyiqa_to_1e6_on_the_same_8_bit_luma():
    a = data.astronaut().astype(np.float64).transpose(2, 0, 1) / 255
    b = ndimage.gaussian_filter(a, (0, 3, 3))

    def luma8(x):  # pyiqa's to_y_channel(x, 255, "yiq"): BT.601 luma rounded to whole levels
        return np.round(np.tensordot([0.299, 0.587, 0.114], x, 1) * 255) / 255

    assert cw_ssim(luma8(a), luma8(b)) == pytest.approx(0.98205313, abs=1e-6)


def test_pyramid_equals_pyrtools():
    pt = pytest.importorskip("pyrtools")
    pyr = pt.pyramids.SteerablePyramidFreq(CAMERA[:200, :300], height=4, order=7, is_complex=True)
    for b, band in enumerate(coarsest_bands(CAMERA[:200, :300])):
        ref = pyr.pyr_coeffs[(3, b)]
        assert np.abs(band - ref).max() <= 1e-10 * np.abs(ref).max()


def test_bad_inputs_are_one_line():
    with pytest.raises(D2TurbError, match="larger image"):
        cw_ssim(np.zeros((40, 40)), np.zeros((40, 40)), levels=4)
    with pytest.raises(D2TurbError, match="larger image"):
        cw_ssim(np.zeros((8, 8)), np.zeros((8, 8)))
    small = CAMERA[:40, :48]  # under 64 px: fewer levels, still 1 on itself
    assert cw_ssim(small, small) == pytest.approx(1.0, abs=1e-12)
    with pytest.raises(D2TurbError, match="one size"):
        cw_ssim(np.zeros((64, 64)), np.zeros((64, 72)))
