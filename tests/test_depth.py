"""Depth providers (d2turb.depth): file loading, CLI spec, weight-free prior, Depth Anything V2."""

import json

import numpy as np
import pytest
import torch
from PIL import Image

from d2turb.depth import depth_for_image, estimate_depth_prior, guided_filter, load_depth, resize_depth
from d2turb.depth.prior import METHODS, box_filter
from d2turb.errors import D2TurbError


def save_png16(path, arr):
    Image.fromarray(arr.astype(np.uint16)).save(path)
    return path


def test_png16_min_max_normalised_with_zeros_as_no_measurement(tmp_path):
    raw = np.tile(np.linspace(1000, 21000, 11).round(), (8, 1))  # metres·256, far to the right
    raw[:, 5] = 0  # missing column: nearest valid neighbour fills it
    d = load_depth(save_png16(tmp_path / "d.png", raw))
    assert d.shape == (1, 8, 11) and d.dtype == torch.float32
    expected = (raw - 1000) / 20000
    valid = raw > 0
    assert np.allclose(d[0].numpy()[valid], expected[valid], atol=1e-6)
    filled = d[0, :, 5].numpy()
    assert np.allclose(filled, expected[:, 4]) or np.allclose(filled, expected[:, 6])


def test_npy_and_8bit_png_agree(tmp_path):
    ramp = np.tile(np.arange(10, dtype=np.float64) * 20 + 5, (6, 1))
    np.save(tmp_path / "a.npy", ramp)
    np.save(tmp_path / "b.npy", ramp[None].astype(np.float32))
    Image.fromarray(ramp.astype(np.uint8)).save(tmp_path / "c.png")
    a, b, c = (load_depth(tmp_path / n) for n in ("a.npy", "b.npy", "c.png"))
    assert torch.allclose(a, b, atol=1e-6) and torch.allclose(a, c, atol=1e-6)
    assert a.min() == 0 and a.max() == 1


def test_disparity_is_inverted_to_depth(tmp_path):
    depth_m = np.tile(np.linspace(2.0, 80.0, 16), (5, 1))
    np.save(tmp_path / "depth.npy", depth_m)
    np.save(tmp_path / "disp.npy", 721.5 * 0.54 / depth_m)  # KITTI stereo relation
    from_disp = load_depth(tmp_path / "disp.npy", is_disparity=True)
    assert torch.allclose(from_disp, load_depth(tmp_path / "depth.npy"), atol=1e-5)
    assert from_disp[0, 0, -1] == 1  # smallest disparity = farthest


def test_near_zero_disparity_does_not_squash_the_scene(tmp_path):
    disp = np.tile(np.linspace(0.0, 1.0, 101), (4, 1))  # affine-invariant disparity: sky ≈ 0
    disp[:, 0] = 1e-9
    np.save(tmp_path / "disp.npy", disp)
    d = load_depth(tmp_path / "disp.npy", is_disparity=True)[0, 0].numpy()
    assert d[0] == 1 and d[-1] == 0
    assert np.all(np.diff(d) <= 1e-7)  # monotone: far → near
    assert d[50] > 0.005  # disparity 0.5 → depth 2 of at most 100: (2 − 1)/(100 − 1)


def test_resize_matches_skimage_bilinear(tmp_path):
    from skimage.transform import resize

    rng = np.random.default_rng(0)
    arr = rng.uniform(1, 10, (10, 13))
    np.save(tmp_path / "d.npy", arr)
    d = load_depth(tmp_path / "d.npy", size=(25, 31))
    ref = resize((arr - arr.min()) / (arr.max() - arr.min()), (25, 31), order=1, mode="edge", anti_aliasing=False)
    assert d.shape == (1, 25, 31)
    assert np.abs(d[0].numpy() - ref).max() < 1e-5
    small = resize_depth(d, (5, 7))
    assert small.shape == (1, 5, 7) and 0 <= small.min() and small.max() <= 1


def test_constant_map_is_all_far(tmp_path):
    np.save(tmp_path / "c.npy", np.full((4, 5), 7.0))
    assert torch.equal(load_depth(tmp_path / "c.npy"), torch.ones(1, 4, 5))


@pytest.mark.parametrize(
    "content, msg",
    [
        (np.array([[1.0, np.nan], [2.0, 3.0]]), "NaN"),
        (np.zeros((3, 3)), "no valid"),
        (np.zeros((2, 3, 3)), "2-D"),
    ],
)
def test_bad_arrays_raise(tmp_path, content, msg):
    np.save(tmp_path / "bad.npy", content)
    with pytest.raises(D2TurbError, match=msg):
        load_depth(tmp_path / "bad.npy")


def test_bad_files_raise(tmp_path):
    with pytest.raises(D2TurbError, match="no such depth file"):
        load_depth(tmp_path / "missing.png")
    (tmp_path / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\nbroken")
    with pytest.raises(D2TurbError, match="cannot read"):
        load_depth(tmp_path / "corrupt.png")
    colour = np.zeros((4, 4, 3), np.uint8)
    colour[..., 0] = 200
    Image.fromarray(colour).save(tmp_path / "turbo.png")
    with pytest.raises(D2TurbError, match="colour-mapped"):
        load_depth(tmp_path / "turbo.png")


def test_depth_for_image_specs(tmp_path, astronaut):
    image = astronaut[0, :, :96, :128]
    assert depth_for_image("none", tmp_path / "x.png", image) is None
    assert depth_for_image(None, tmp_path / "x.png", image) is None
    prior = depth_for_image("prior", tmp_path / "x.png", image)
    assert prior.shape == (1, 96, 128) and torch.equal(prior, estimate_depth_prior(image))
    folder = tmp_path / "depths"
    folder.mkdir()
    save_png16(folder / "scene.png", np.tile(np.linspace(1, 100, 64), (48, 1)))
    by_dir = depth_for_image(str(folder), tmp_path / "imgs" / "scene.jpg", image)
    by_file = depth_for_image(str(folder / "scene.png"), None, image)
    assert by_dir.shape == (1, 96, 128) and torch.equal(by_dir, by_file)
    inverted = depth_for_image(str(folder / "scene.png"), None, image, is_disparity=True)
    assert inverted[0, 48, 0] > inverted[0, 48, -1]
    with pytest.raises(D2TurbError, match="other.jpg"):
        depth_for_image(str(folder), tmp_path / "other.jpg", image)
    with pytest.raises(D2TurbError, match="expected none, prior"):
        depth_for_image(str(tmp_path / "nope"), None, image)
    with pytest.raises(D2TurbError, match="Depth Anything model folder"):
        depth_for_image(f"anything:{tmp_path / 'no_model'}", None, image)


# ---- weight-free prior ---------------------------------------------------------------------------


def test_box_filter_matches_scipy_uniform_filter_inside():
    from scipy.ndimage import uniform_filter

    x = torch.rand(1, 1, 30, 40, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    ref = uniform_filter(x[0, 0].numpy(), size=7)
    assert np.allclose(box_filter(x, 3)[0, 0].numpy()[3:-3, 3:-3], ref[3:-3, 3:-3], atol=1e-12)


def test_guided_filter_preserves_edges_smooths_flat_regions():
    guide = torch.zeros(1, 1, 32, 32, dtype=torch.float64)
    guide[..., 16:] = 1.0
    noise = 0.05 * torch.randn(1, 1, 32, 32, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    out = guided_filter(guide, guide + noise, r=4, eps=1e-4)
    # step edge kept (He et al.: a ≈ 1 where var(I) ≫ ε), noise reduced
    assert (out - guide).abs()[..., :, 13:19].max() < 0.2
    assert (out - guide).std() < 0.5 * noise.std()


@pytest.mark.parametrize("method", METHODS)
def test_prior_shapes_range_and_orientation(method, astronaut):
    image = torch.nn.functional.interpolate(astronaut, size=(64, 80), mode="area")
    d = estimate_depth_prior(image[0], method)
    assert d.shape == (1, 64, 80) and 0 <= d.min() and d.max() <= 1 and torch.isfinite(d).all()
    if "vertical" in method:  # top of the frame farther
        assert d[:, :8].mean() > d[:, -8:].mean()
    batch = estimate_depth_prior(torch.cat([image, image.flip(-1)]), method)
    assert batch.shape == (2, 1, 64, 80)
    assert torch.allclose(batch[0], d, atol=1e-6)


def test_haze_cue_orders_a_synthetic_hazy_scene():
    # Koschmieder: I = J·t + A(1 − t), t = e^(−βd); ground truth depth increases to the top
    h, w = 96, 96
    g = torch.Generator().manual_seed(0)
    truth = torch.linspace(1, 0, h).view(1, 1, h, 1).expand(1, 1, h, w)
    scene = torch.rand(1, 3, h // 8, w // 8, generator=g) * 0.6
    scene = torch.nn.functional.interpolate(scene, size=(h, w), mode="nearest")
    scene[:, :, (torch.arange(h * w) % 3).view(h, w) == 0] = 0  # dark pixels in every patch (dark-channel prior)
    t = torch.exp(-2.5 * truth)
    hazy = scene * t + 0.9 * (1 - t)
    est = estimate_depth_prior(hazy[0], "haze")
    from scipy.stats import spearmanr

    assert spearmanr(est.flatten().numpy(), truth.flatten().numpy()).statistic > 0.8


def test_prior_rejects_bad_input():
    with pytest.raises(D2TurbError, match="RGB"):
        estimate_depth_prior(torch.rand(1, 8, 8))
    with pytest.raises(D2TurbError, match="NaN"):
        estimate_depth_prior(torch.full((3, 8, 8), float("nan")))
    with pytest.raises(D2TurbError, match="method"):
        estimate_depth_prior(torch.rand(3, 8, 8), "magic")


KITTI_FLOOR = 0.85  # measured mean Spearman of the default: 0.869 (docs/depth.md)


def test_default_prior_beats_vertical_baseline_on_kitti(shared_data):
    from d2turb.depth.evaluate import kitti_cases, spearman_on_valid
    from d2turb.io import read_image

    cases = kitti_cases(shared_data / "depth")
    if not cases:
        pytest.skip("no KITTI depth data")
    default, vertical = [], []
    for rgb, gt, valid in cases:
        image = read_image(rgb)
        default.append(spearman_on_valid(estimate_depth_prior(image), gt, valid))
        vertical.append(spearman_on_valid(estimate_depth_prior(image, "vertical"), gt, valid))
    assert np.mean(default) >= np.mean(vertical)
    assert np.mean(default) >= KITTI_FLOOR


# ---- Depth Anything V2 (tiny random model, no download) --------------------------------------------


@pytest.fixture(scope="module")
def tiny_depth_anything(tmp_path_factory):
    transformers = pytest.importorskip("transformers")
    torch.manual_seed(0)
    backbone = transformers.Dinov2Config(
        hidden_size=32,
        num_hidden_layers=4,
        num_attention_heads=2,
        intermediate_size=64,
        patch_size=14,
        image_size=56,
        out_features=["stage1", "stage2", "stage3", "stage4"],
        reshape_hidden_states=False,
    )
    config = transformers.DepthAnythingConfig(
        backbone_config=backbone,
        reassemble_hidden_size=32,
        neck_hidden_sizes=[8, 16, 32, 32],
        fusion_hidden_size=16,
        head_hidden_size=8,
        patch_size=14,
    )
    folder = tmp_path_factory.mktemp("tiny_da")
    transformers.DepthAnythingForDepthEstimation(config).save_pretrained(folder)
    return folder


@pytest.mark.slow
def test_depth_anything_tiny_model(tiny_depth_anything):
    from d2turb.depth import DepthAnything

    model = DepthAnything(tiny_depth_anything, input_size=56)
    image = torch.rand(3, 50, 70, generator=torch.Generator().manual_seed(0))
    d = model(image)
    assert d.shape == (1, 50, 70) and d.dtype == torch.float32
    assert d.min() == 0 and d.max() == 1
    disp = model.disparity(image)
    assert disp.shape == (1, 1, 50, 70)
    # far = 1 where disparity is smallest (near = large disparity)
    flat_d, flat_disp = d.flatten(), disp.flatten()
    assert flat_d[flat_disp.argmin()] == 1 and flat_d[flat_disp.argmax()] == 0
    assert model(torch.stack([image, image])).shape == (2, 1, 50, 70)
    via_spec = depth_for_image(f"anything:{tiny_depth_anything}", None, image)
    assert via_spec.shape == (1, 50, 70)


def test_depth_anything_reads_processor_config(tiny_depth_anything, tmp_path):
    import shutil

    from d2turb.depth import DepthAnything

    folder = tmp_path / "with_processor"
    shutil.copytree(tiny_depth_anything, folder)
    (folder / "preprocessor_config.json").write_text(
        json.dumps(
            {
                "size": {"height": 28, "width": 28},
                "ensure_multiple_of": 14,
                "image_mean": [0.5] * 3,
                "image_std": [0.5] * 3,
            }
        )
    )
    model = DepthAnything(folder)
    assert model.input_size == 28 and model.mean == (0.5, 0.5, 0.5)
    assert model._input_shape(50, 70) == (28, 42)


def test_depth_anything_missing_or_broken_folder(tmp_path):
    from d2turb.depth import DepthAnything

    with pytest.raises(D2TurbError, match="not found"):
        DepthAnything(tmp_path / "absent")
    pytest.importorskip("transformers")  # without it the folder is refused for that reason instead
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "config.json").write_text("{}")
    with pytest.raises(D2TurbError, match="cannot load"):
        DepthAnything(tmp_path / "broken")
