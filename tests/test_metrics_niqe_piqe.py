"""NIQE and PIQE against the original MATLAB outputs on the IQA-PyTorch calibration images."""

import numpy as np
import pytest
import torch

from d2turb.errors import D2TurbError
from d2turb.eval.niqe import MATLAB_GREY_WEIGHTS, imresize, matlab_grey_uint8, niqe, pristine_model
from d2turb.eval.piqe import piqe
from d2turb.io import read_image

# NIQE of the original LIVE MATLAB release (rgb2gray, no border crop), from ../shared/data/SOURCES.md
# (also the "niqe" row of IQA-PyTorch ResultsCalibra/calibration_summary.csv).
NIQE_MATLAB = {"I03": 15.7536, "I04": 3.6549, "I06": 3.2355, "I08": 3.1840, "I19": 8.6352}
# MATLAB `piqe` (Image Processing Toolbox) on the same images: the "piqe" row of
# https://github.com/chaofengc/IQA-PyTorch/blob/main/ResultsCalibra/calibration_summary.csv
# (values printed with 2 decimals).
PIQE_MATLAB = {"I03": 100.0, "I04": 21.62, "I06": 35.86, "I08": 41.15, "I19": 76.95}


@pytest.fixture
def calibration(shared_data):
    folder = shared_data / "iqa_calibration" / "dist"
    if not folder.is_dir():
        pytest.skip(f"{folder} is absent")
    return {name: read_image(folder / f"{name}.png") for name in NIQE_MATLAB}


def test_niqe_matches_matlab_golden_values(calibration):
    for name, expected in NIQE_MATLAB.items():
        assert niqe(calibration[name]).item() == pytest.approx(expected, abs=0.05), name


def test_piqe_matches_matlab_golden_values(calibration):
    for name, expected in PIQE_MATLAB.items():
        assert piqe(calibration[name]).item() == pytest.approx(expected, abs=0.01), name


def test_batched_equals_single(calibration):
    batch = torch.stack([calibration["I04"], calibration["I06"]])
    assert niqe(batch).tolist() == [niqe(calibration["I04"]).item(), niqe(calibration["I06"]).item()]
    assert piqe(batch).tolist() == [piqe(calibration["I04"]).item(), piqe(calibration["I06"]).item()]


def test_packaged_pristine_model_is_the_shared_one(shared_data):
    shared = np.load(shared_data / "iqa_calibration" / "niqe_pristine_params.npz")
    mu, cov, window = pristine_model()
    np.testing.assert_array_equal(mu, shared["mu_pris_param"].ravel())
    np.testing.assert_array_equal(cov, shared["cov_pris_param"])
    np.testing.assert_array_equal(window, shared["gaussian_window"])


def test_pristine_model_shape_and_window():
    mu, cov, window = pristine_model()
    assert mu.shape == (36,) and cov.shape == (36, 36)
    np.testing.assert_allclose(cov, cov.T)
    x = np.arange(7) - 3.0  # fspecial('gaussian', 7, 7/6)
    g = np.exp(-(x[:, None] ** 2 + x[None] ** 2) / (2 * (7 / 6) ** 2))
    np.testing.assert_allclose(window, g / g.sum(), atol=1e-12)


def test_grey_conversion_is_matlab_rgb2gray():
    np.testing.assert_allclose(MATLAB_GREY_WEIGHTS, (0.2989, 0.5870, 0.1140), atol=6e-5)  # documented 4 digits
    rgb = torch.tensor([[[1.0]], [[0.5]], [[0.0]]])  # (3,1,1): 255, 128 (rounded), 0
    expected = np.floor(255 * MATLAB_GREY_WEIGHTS[0] + 128 * MATLAB_GREY_WEIGHTS[1] + 0.5)
    assert matlab_grey_uint8(rgb)[0, 0] == expected == 151


def test_imresize_half_matches_matlab_rules():
    # constant stays constant (weights sum to 1, symmetric padding)
    np.testing.assert_allclose(imresize(np.full((10, 12), 7.0), 0.5), 7.0)
    out = imresize(np.arange(16.0).reshape(4, 4), 0.5)
    assert out.shape == (2, 2)
    # a linear ramp is reproduced exactly away from the borders (the cubic kernel reproduces linears)
    ramp = np.tile(np.arange(64.0), (64, 1))
    mid = imresize(ramp, 0.5)[:, 8:24]
    np.testing.assert_allclose(mid, (2 * np.arange(8, 24) + 0.5)[None].repeat(32, 0), atol=1e-9)


def test_noise_raises_both_scores(astronaut):
    g = torch.Generator().manual_seed(0)
    img = astronaut[0]
    noisy = [(img + s * torch.randn(img.shape, generator=g)).clamp(0, 1) for s in (0.0, 0.05, 0.15)]
    n = [niqe(x).item() for x in noisy]
    assert n[0] < n[1] < n[2]
    p = [piqe(x).item() for x in noisy]
    assert p[0] < p[2]


def test_flat_image_piqe_is_100_and_small_image_niqe_errors():
    assert piqe(torch.full((3, 40, 50), 0.3)).item() == 100.0  # MATLAB doc: uniform image → 100
    with pytest.raises(D2TurbError, match="at least 96x96"):
        niqe(torch.rand(3, 80, 200))
    with pytest.raises(D2TurbError, match="shape"):
        niqe(torch.rand(2, 100, 100))


def test_niqe_skips_flat_blocks_and_rejects_flat_images(astronaut):
    img = torch.nn.functional.interpolate(astronaut, size=(288, 288), mode="bilinear", align_corners=False)[0]
    img[:, :192, :192] = 0.5  # block (0, 0) is perfectly flat: its AGGD fits are 0/0; MATLAB nan* skip it
    value = niqe(img).item()
    assert np.isfinite(value) and value > 0
    with pytest.raises(D2TurbError, match="textured"):
        niqe(torch.full((3, 200, 200), 0.5))
