"""d2turb.eval.artifacts: each measure of the real clips report against an independent oracle (a codec, a known
noise σ, a known tone curve, a known ghost, the Gaussian edge's peak gradient)."""

import math

import cv2
import numpy as np
import pytest
from scipy.stats import norm
from skimage import data

from d2turb.eval import artifacts


def _natural(size=512):
    grey = data.camera()  # 512², uncompressed (PNG)
    return cv2.resize(grey, (size, size), interpolation=cv2.INTER_AREA)


def _jpeg(grey_u8, quality):
    ok, buf = cv2.imencode(".jpg", grey_u8, [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    return cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)


def test_block_energy_sees_the_jpeg_grid_and_not_an_uncompressed_image():
    img = _natural()
    plain = artifacts.block_energy(img)
    assert abs(plain - 1) < 0.05  # no grid: boundaries are like any other column
    low = artifacts.block_energy(_jpeg(img, 10))
    assert low > 1.3 and low > artifacts.block_energy(_jpeg(img, 50)) > plain
    # the grid moved off the frame's 8-px lattice (a 4-px crop) is not the frame's grid
    assert abs(artifacts.block_energy(_jpeg(img, 10)[4:, 4:]) - 1) < abs(low - 1) / 3


def test_block_map_finds_the_blocked_region():
    img = _natural()
    mixed = img.copy()
    mixed[256:384, 128:256] = _jpeg(img, 5)[256:384, 128:256]
    y, x = artifacts.worst_window(artifacts.block_map(mixed) - artifacts.block_map(img), 128)
    assert abs(y - 256) <= 16 and abs(x - 128) <= 16


def _noise_tolerance(sigma, n_pixels):
    """3 standard errors of Immerkær's estimate: √(π/2 - 1) σ / √n for n independent samples of |I * N|, with n the
    pixels over 25 (a pixel's 5×5 neighbourhood shares mask support with it): conservative."""
    return 3 * math.sqrt(math.pi / 2 - 1) * sigma / math.sqrt(n_pixels / 25)


@pytest.mark.parametrize("sigma", [0.005, 0.02])
def test_flat_noise_sigma_returns_a_known_sigma(sigma):
    rng = np.random.default_rng(1)
    flat = np.full((512, 512), 0.5, np.float32) + rng.normal(0, sigma, (512, 512)).astype(np.float32)
    est = artifacts.flat_noise_sigma(flat)
    n = artifacts.NOISE_SHARE * 512 * 512
    assert abs(est - sigma) < _noise_tolerance(sigma, n)


def test_flat_noise_sigma_ignores_structure_outside_the_flat_blocks():
    rng = np.random.default_rng(2)
    sigma = 0.01
    scene = _natural().astype(np.float32) / 255
    scene[:, :256] = 0.3  # a flat half beside the photograph
    noisy = scene + rng.normal(0, sigma, scene.shape).astype(np.float32)
    est = artifacts.flat_noise_sigma(noisy)
    assert abs(est - sigma) < _noise_tolerance(sigma, artifacts.NOISE_SHARE * 512 * 512)
    # clipped black is flat but hides noise: not among the flat blocks
    clipped = noisy.copy()
    clipped[:128] = np.clip(rng.normal(0, sigma, (128, 512)), 0, 1)  # mean luma 0, half the pixels clipped
    assert abs(artifacts.flat_noise_sigma(clipped) - sigma) < _noise_tolerance(sigma, artifacts.NOISE_SHARE * 384 * 512)
    # measured in the reference's flat blocks: a denoised copy reads less there
    smooth = cv2.GaussianBlur(noisy, (0, 0), 2)
    assert artifacts.flat_noise_sigma(smooth, reference=noisy) < 0.3 * sigma


def test_tail_fractions_see_shadows_crushed_by_a_known_tone_curve():
    levels = np.tile(np.arange(256, dtype=np.float32), (64, 1))  # each 8-bit level in 64 pixels (one column)
    before = levels / 255
    # the tone curve y = (x - 16) · 255/223, clipped: 8-bit levels x ≤ 19 go to < 4.5 → ≤ 4 (20 levels), x ≥ 236
    # go to > 250.5 → ≥ 251 (20 levels); before: 5 levels near black (0–4), 5 near white (251–255)
    after = np.clip((levels - 16) * 255 / 223, 0, 255) / 255
    black0, white0 = artifacts.tail_fractions(before)
    black1, white1 = artifacts.tail_fractions(after)
    assert black0 == pytest.approx(5 / 256) and white0 == pytest.approx(5 / 256)
    assert black1 - black0 == pytest.approx(15 / 256) and white1 - white0 == pytest.approx(15 / 256)
    rgb = np.repeat(after[..., None], 3, axis=2)  # grey as RGB: the same luma
    assert artifacts.tail_fractions(rgb) == pytest.approx((black1, white1))


def _steps(shape=(192, 256)):
    """A grey field with two dark and one bright rectangle (sharp step edges of 0.3–0.4)."""
    img = np.full(shape, 0.5, np.float32)
    img[40:100, 40:120] = 0.15
    img[120:170, 150:230] = 0.9
    img[60:150, 170:200] = 0.2
    return img


def _shift(img, dx, dy):
    m = np.float32([[1, 0, dx], [0, 1, dy]])
    return cv2.warpAffine(img, m, img.shape[::-1], flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def test_a_ghosted_copy_of_step_edges_is_flagged_and_a_single_one_is_not():
    rng = np.random.default_rng(3)
    scene = _steps()
    frame = scene + rng.normal(0, 0.01, scene.shape).astype(np.float32)  # the input frame at its pose
    ghost = 0.5 * scene + 0.5 * _shift(scene, 7, 5)  # a frame fused at the wrong pose as well: doubled edges
    assert artifacts.ghost_share(ghost, frame) > 0.3
    single = [
        scene,  # the noise removed
        cv2.GaussianBlur(scene, (0, 0), 1.5),  # softer
        np.clip(scene + 1.0 * (scene - cv2.GaussianBlur(scene, (0, 0), 1.0)), 0, 1),  # sharpened (unsharp mask)
        _shift(scene, 4.3, -2.6),  # the whole output off its input's pose: not a ghost
    ]
    for image in single:
        assert artifacts.ghost_share(image, frame) < 0.05
    y, x = artifacts.worst_window(artifacts.ghost_map(ghost, frame), 48)
    assert artifacts.ghost_map(ghost, frame)[y : y + 48, x : x + 48].sum() > 0


def _blurred_step(sigma, amplitude=0.6, shape=(64, 128)):
    """A vertical step of ``amplitude`` at x = 63.5 blurred by a Gaussian of ``sigma`` px, sampled exactly (erf)."""
    x = np.arange(shape[1]) - 63.5
    row = 0.2 + amplitude * norm.cdf(x / sigma)
    return np.tile(row.astype(np.float32), (shape[0], 1))


def test_edge_sharpness_falls_with_blur_as_the_gaussian_edge_peak():
    sigmas = [0.3, 0.7, 1.0, 1.5, 2.0, 3.0, 4.0]
    values = [artifacts.edge_sharpness(_blurred_step(s), reference=_blurred_step(0.3)) for s in sigmas]
    assert all(a > b for a, b in zip(values, values[1:], strict=False))
    for s, v in zip(sigmas, values, strict=True):
        # the sampled profile's largest central difference, A [Φ((x+1-e)/σ) - Φ((x-1-e)/σ)] / 2 at the pixels x
        # beside the edge e = 63.5: its peak, which falls as A / (σ √(2π)) for a wide blur
        x = np.arange(60, 68) - 63.5
        peak = (0.6 * (norm.cdf((x + 1) / s) - norm.cdf((x - 1) / s)) / 2).max()
        assert v == pytest.approx(peak, rel=1e-3)
    # on a photograph too: each blur is less sharp at the original's strongest edges
    img = _natural(256).astype(np.float32) / 255
    blurred = [img] + [cv2.GaussianBlur(img, (0, 0), s) for s in (0.8, 1.6, 3.2)]
    values = [artifacts.edge_sharpness(b, reference=img) for b in blurred]
    assert all(a > b for a, b in zip(values, values[1:], strict=False))


def test_sharpness_loss_map_finds_the_blurred_region():
    img = _natural(256).astype(np.float32) / 255
    soft = img.copy()
    soft[128:192, 32:96] = cv2.GaussianBlur(img, (0, 0), 3)[128:192, 32:96]
    sharp = np.clip(img + 1.5 * (img - cv2.GaussianBlur(img, (0, 0), 1.0)), 0, 1)  # sharper elsewhere
    for image in (soft, np.where(np.abs(np.arange(256) - 160)[None] < 64, img, sharp).astype(np.float32)):
        image[128:192, 32:96] = soft[128:192, 32:96]
        y, x = artifacts.worst_window(artifacts.sharpness_loss_map(image, img), 64)
        assert abs(y - 128) <= 16 and abs(x - 32) <= 16


def test_tail_and_noise_maps_find_their_regions():
    img = _natural(256).astype(np.float32) / 255
    crushed = img.copy()
    crushed[16:80, 160:224] = np.clip(img[16:80, 160:224] - 0.8, 0, 1)
    tails = np.abs(artifacts.tail_map(crushed)).astype(np.float32) - np.abs(artifacts.tail_map(img))
    y, x = artifacts.worst_window(tails, 64)
    assert abs(y - 16) <= 16 and abs(x - 160) <= 16
    flat = np.full((256, 256), 0.4, np.float32)
    noisy = flat.copy()
    noisy[128:192, 64:128] += np.random.default_rng(4).normal(0, 0.02, (64, 64)).astype(np.float32)
    noise = artifacts.noise_map(noisy, reference=flat, share=1.0) - artifacts.noise_map(flat, share=1.0)
    y, x = artifacts.worst_window(noise, 64)
    assert abs(y - 128) <= 8 and abs(x - 64) <= 8


def test_edge_sharpness_reads_a_frame_moved_as_a_whole_as_sharp_as_in_place():
    """A restored frame of a shaken clip sits a few px off its input frame as a whole: read against that frame, it is
    as sharp as the same frame in place (the edges found after the global move), and a blurred one still less sharp."""
    img = _natural(256).astype(np.float32) / 255
    moved = np.roll(img, (7, -9), axis=(0, 1))
    here = artifacts.edge_sharpness(img, reference=img)
    assert artifacts.edge_sharpness(moved, reference=img) == pytest.approx(here, rel=0.03)
    blurred = np.roll(cv2.GaussianBlur(img, (0, 0), 1.5), (7, -9), axis=(0, 1))
    assert artifacts.edge_sharpness(blurred, reference=img) < 0.8 * here
