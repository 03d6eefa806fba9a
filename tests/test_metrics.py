"""PSNR / SSIM against scikit-image, accumulator semantics and DDP (2 gloo processes) equivalence."""

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity
from test_metrics_ddp import _pairs

from d2turb.errors import D2TurbError
from d2turb.eval.metrics import PSNR, SSIM, KeyedMean, psnr, quantise_8bit, ssim


@pytest.fixture(autouse=True)
def _one_thread():
    """Small tensors: one thread avoids OpenMP stalls when the shared 2-core machine is oversubscribed."""
    torch.set_num_threads(1)


def _hwc(x):
    return x.permute(1, 2, 0).double().numpy()


@pytest.fixture
def noisy_astronaut(astronaut):
    g = torch.Generator().manual_seed(1)
    noisy = (astronaut + 0.08 * torch.randn(astronaut.shape, generator=g)).clamp(0, 1)
    blurred = torch.nn.functional.avg_pool2d(astronaut, 5, 1, 2, count_include_pad=False)
    return torch.cat([noisy, blurred]), torch.cat([astronaut, astronaut])


def test_psnr_matches_skimage_per_image(noisy_astronaut):
    pred, target = noisy_astronaut
    ours = psnr(pred, target)
    assert ours.shape == (2,)
    for i in range(2):
        ref = peak_signal_noise_ratio(_hwc(target[i]), _hwc(pred[i]), data_range=1.0)
        assert ours[i].item() == pytest.approx(ref, abs=1e-6)


def test_psnr_identical_images_is_capped_not_inf(astronaut):
    assert psnr(astronaut, astronaut).item() == pytest.approx(100.0)


@pytest.mark.parametrize("gaussian", [True, False])
def test_ssim_matches_skimage(noisy_astronaut, gaussian):
    pred, target = noisy_astronaut
    ours = ssim(pred, target, gaussian=gaussian)
    for i in range(2):
        if gaussian:  # Wang et al. setting
            ref = structural_similarity(
                _hwc(pred[i]),
                _hwc(target[i]),
                channel_axis=-1,
                data_range=1.0,
                gaussian_weights=True,
                sigma=1.5,
                use_sample_covariance=False,
            )
        else:  # skimage default: 7x7 uniform window, sample covariance
            ref = structural_similarity(_hwc(pred[i]), _hwc(target[i]), channel_axis=-1, data_range=1.0)
        assert ours[i].item() == pytest.approx(ref, abs=1e-3)  # the requirement
        assert ours[i].item() == pytest.approx(ref, abs=1e-4)  # float32 filtering is in fact ~1e-6 away
        f64 = ssim(pred[i : i + 1].double(), target[i : i + 1].double(), gaussian=gaussian)
        assert f64.item() == pytest.approx(ref, abs=1e-8)  # float64 input: equal to float64 precision


def test_ssim_properties(astronaut):
    assert ssim(astronaut, astronaut).item() == pytest.approx(1.0, abs=1e-9)
    levels = [
        ssim((astronaut + s * torch.randn_like(astronaut)).clamp(0, 1), astronaut).item() for s in (0.02, 0.1, 0.3)
    ]
    assert levels[0] > levels[1] > levels[2]


def test_single_image_and_bad_inputs(astronaut):
    assert psnr(astronaut[0], astronaut[0] * 0.9).shape == (1,)
    with pytest.raises(D2TurbError, match="shapes differ"):
        psnr(astronaut, astronaut[..., :100])
    with pytest.raises(D2TurbError, match="NaN"):
        ssim(astronaut * float("nan"), astronaut)
    with pytest.raises(D2TurbError, match="smaller than"):
        ssim(astronaut[..., :8, :8], astronaut[..., :8, :8])


def test_accumulator_mean_of_per_image_values_and_reset():
    pred, target = _pairs()
    metric = PSNR()
    metric.update(pred[:2], target[:2])
    metric.update(pred[2:], target[2:])
    assert metric.compute() == pytest.approx(psnr(pred, target).mean().item(), abs=1e-9)
    metric.reset()
    assert np.isnan(metric.compute())
    s = SSIM()
    s.update(pred[:1], target[:1])
    s.update(pred[1:], target[1:])
    assert s.compute() == pytest.approx(ssim(pred, target).mean().item(), abs=1e-9)


def test_keyed_mean_equals_numpy_means_per_key_and_group():
    rng = np.random.default_rng(3)
    n = 23
    values = {"psnr": rng.normal(30, 5, n), "epe": rng.gamma(2.0, 0.5, n)}
    bins = rng.integers(0, 3, n)
    mean = KeyedMean()
    for start, stop in ((0, 5), (5, 6), (6, 17), (17, n)):  # uneven batches; tensors, a list and floats
        epe = [float(v) for v in values["epe"][start:stop]]  # Python floats are float64, not torch's default float32
        batch = {"psnr": torch.from_numpy(values["psnr"][start:stop]), "epe": epe if len(epe) > 1 else epe[0]}
        mean.update(batch, groups=torch.from_numpy(bins[start:stop]))
    assert mean.compute() == pytest.approx({k: np.mean(v) for k, v in values.items()}, rel=1e-12)
    assert mean.groups() == list(dict.fromkeys(bins.tolist()))
    for b in range(3):
        chosen = bins == b
        assert mean.compute(b) == pytest.approx({k: np.mean(v[chosen]) for k, v in values.items()}, rel=1e-12)
        assert mean.count("psnr", b) == chosen.sum()
    assert mean.count("psnr") == n and mean.count("psnr", 7) == 0 and mean.compute(7) == {}
    single = KeyedMean()  # one label for a whole batch; a float is one sample
    single.update({"a": 1.0}, groups="weak")
    single.update({"a": torch.tensor([2.0, 6.0])}, groups="strong")
    single.update({"b": torch.zeros(0)}, groups="weak")  # no samples: no mean
    assert single.compute() == {"a": 3.0} and single.compute("weak") == {"a": 1.0}
    assert single.compute("strong") == {"a": 4.0} and single.groups() == ["weak", "strong"]
    with pytest.raises(D2TurbError, match="2 group labels for 3 values"):
        single.update({"a": torch.ones(3)}, groups=[0, 1])
    single.reset()
    assert single.compute() == {} and single.groups() == []


def test_quantise_8bit_is_what_an_8bit_png_holds():
    # clamped to [0, 1], then the nearest multiple of 1/255: the 8-bit levels worked out by hand
    x = torch.tensor([-0.1, 0.0, 0.4 / 255, 0.6 / 255, 76.4 / 255, 1.2])
    expected = np.array([0, 0, 0, 1, 76, 255], np.uint8).astype(np.float32) / 255
    np.testing.assert_allclose(quantise_8bit(x).numpy(), expected, rtol=0, atol=1e-7)
