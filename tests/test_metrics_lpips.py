"""LPIPS from local files: torchvision / lpips-package key layouts, path resolution, errors.

Real weights are never needed: random weights with the real shapes are written to tmp files, and the
network is checked against an independent functional re-derivation of LPIPS (Zhang et al. 2018, Eq. 1).
"""

import pytest
import torch
import torch.nn.functional as F
from safetensors.torch import save_file

from d2turb.errors import D2TurbError
from d2turb.eval.lpips import LPIPS, lpips
from d2turb.eval.metrics import LPIPSMetric
from d2turb.eval.vgg import FeatureExtractor, imagenet_normalize

# torchvision alexnet().features / vgg16().features conv layers: index -> (out, in, k)
ALEX_CONVS = {0: (64, 3, 11), 3: (192, 64, 5), 6: (384, 192, 3), 8: (256, 384, 3), 10: (256, 256, 3)}
VGG_CONVS = dict(
    zip(
        [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28],
        [
            (64, 3),
            (64, 64),
            (128, 64),
            (128, 128),
            (256, 128),
            (256, 256),
            (256, 256),
            (512, 256),
            (512, 512),
            (512, 512),
            (512, 512),
            (512, 512),
            (512, 512),
        ],
    )
)
LIN_CHANNELS = {"alex": (64, 192, 384, 256, 256), "vgg": (64, 128, 256, 512, 512)}


@pytest.fixture(autouse=True)
def _one_thread():
    """Small tensors: one thread avoids OpenMP stalls when the shared 2-core machine is oversubscribed."""
    torch.set_num_threads(1)


def _alex_state(seed=0):
    g = torch.Generator().manual_seed(seed)
    state = {}
    for i, (o, c, k) in ALEX_CONVS.items():
        state[f"features.{i}.weight"] = torch.randn(o, c, k, k, generator=g) * (2 / (c * k * k)) ** 0.5
        state[f"features.{i}.bias"] = torch.randn(o, generator=g) * 0.01
    state["classifier.6.weight"] = torch.zeros(10, 4)  # torchvision files carry a classifier: ignored
    return state


def _vgg_state(seed=0):
    g = torch.Generator().manual_seed(seed)
    state = {}
    for i, (o, c) in VGG_CONVS.items():
        state[f"features.{i}.weight"] = torch.randn(o, c, 3, 3, generator=g) * (2 / (c * 9)) ** 0.5
        state[f"features.{i}.bias"] = torch.zeros(o)
    return state


def _lin_state(net, seed=1):
    g = torch.Generator().manual_seed(seed)
    return {f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1, generator=g) for i, c in enumerate(LIN_CHANNELS[net])}


@pytest.fixture
def alex_files(tmp_path):
    backbone, lin = tmp_path / "alexnet-owt-7be5be79.pth", tmp_path / "alex.pth"
    torch.save(_alex_state(), backbone)
    torch.save(_lin_state("alex"), lin)
    return backbone, lin


@pytest.fixture(autouse=True)
def _no_user_weights(monkeypatch, tmp_path):
    """Keep the user's environment and cache out of these tests."""
    monkeypatch.delenv("D2TURB_LPIPS_WEIGHTS", raising=False)
    monkeypatch.delenv("D2TURB_LPIPS_BACKBONE", raising=False)
    monkeypatch.setenv("D2TURB_CACHE_DIR", str(tmp_path / "empty_cache"))


# The normalisation every torchvision ImageNet model expects, as published in the torchvision model docs
# (mean and std of the ImageNet training set per RGB channel, for images in [0, 1]).
TORCHVISION_IMAGENET_MEAN = (0.485, 0.456, 0.406)
TORCHVISION_IMAGENET_STD = (0.229, 0.224, 0.225)


def _oracle_alex_lpips(x0, x1, backbone, lins):
    """LPIPS written out from Zhang et al. 2018, Eq. 1: AlexNet relu1..5 of the ImageNet-normalised image,
    unit-normalise over channels, weighted squared difference, mean over pixels, sum over layers.

    The input normalisation is taken from torchvision's published ImageNet statistics on [0, 1] images, not from
    LPIPS' ScalingLayer: that layer (lpips/lpips.py) works on [−1, 1] images with shift (−.030, −.088, −.188) and
    scale (.458, .448, .450), which are exactly 2·mean − 1 and 2·std, i.e. the same map."""
    mean = torch.tensor(TORCHVISION_IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(TORCHVISION_IMAGENET_STD).view(1, 3, 1, 1)

    def taps(x):
        x = (x - mean) / std
        w = lambda i: (backbone[f"features.{i}.weight"], backbone[f"features.{i}.bias"])  # noqa: E731
        r1 = F.relu(F.conv2d(x, *w(0), stride=4, padding=2))
        r2 = F.relu(F.conv2d(F.max_pool2d(r1, 3, 2), *w(3), padding=2))
        r3 = F.relu(F.conv2d(F.max_pool2d(r2, 3, 2), *w(6), padding=1))
        r4 = F.relu(F.conv2d(r3, *w(8), padding=1))
        r5 = F.relu(F.conv2d(r4, *w(10), padding=1))
        return [r1, r2, r3, r4, r5]

    d = 0
    for i, (a, b) in enumerate(zip(taps(x0), taps(x1))):
        a = a / (a.norm(dim=1, keepdim=True) + 1e-10)
        b = b / (b.norm(dim=1, keepdim=True) + 1e-10)
        w = lins[f"lin{i}.model.1.weight"].view(1, -1, 1, 1)
        d = d + (w * (a - b) ** 2).sum(1).mean(dim=(1, 2))
    return d


def _images(n=2, size=64, seed=3):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, size, size, generator=g)
    y = (x + 0.2 * torch.randn(x.shape, generator=g)).clamp(0, 1)
    return x, y


def test_alex_lpips_matches_oracle_identity_and_determinism(alex_files):
    backbone, lin = alex_files
    model = LPIPS("alex", weights=lin, backbone=backbone)
    x, y = _images()
    d = model(x, y)
    assert d.shape == (2,)
    torch.testing.assert_close(d, _oracle_alex_lpips(x, y, _alex_state(), _lin_state("alex")), rtol=1e-5, atol=1e-7)
    assert (d > 0).all()
    assert torch.equal(model(x, y), d)  # deterministic
    torch.testing.assert_close(model(y, x), d, rtol=1e-6, atol=1e-8)  # symmetric
    assert torch.equal(model(x, x), torch.zeros(2))
    # monotone in the distortion strength
    assert (model(x, (x + 0.05 * (y - x))) < d).all()


def test_paths_from_env_vars_cache_folder_and_safetensors(alex_files, tmp_path, monkeypatch):
    backbone, lin = alex_files
    x, y = _images(1)
    expected = LPIPS("alex", weights=lin, backbone=backbone)(x, y)

    st_dir = tmp_path / "st"
    st_dir.mkdir()
    save_file(_alex_state(), str(st_dir / "alexnet.safetensors"))
    save_file(_lin_state("alex"), str(st_dir / "alex.safetensors"))
    monkeypatch.setenv("D2TURB_LPIPS_BACKBONE", str(st_dir / "alexnet.safetensors"))  # a file
    monkeypatch.setenv("D2TURB_LPIPS_WEIGHTS", str(st_dir))  # a folder holding alex.safetensors
    torch.testing.assert_close(LPIPS("alex")(x, y), expected)

    monkeypatch.delenv("D2TURB_LPIPS_BACKBONE")
    monkeypatch.delenv("D2TURB_LPIPS_WEIGHTS")
    cache = tmp_path / "cache"
    (cache / "lpips").mkdir(parents=True)
    backbone.rename(cache / "alexnet-owt-7be5be79.pth")  # torchvision's file name
    lin.rename(cache / "lpips" / "alex.pth")  # the lpips package's file name
    monkeypatch.setenv("D2TURB_CACHE_DIR", str(cache))
    torch.testing.assert_close(lpips(x, y), expected)
    metric = LPIPSMetric(net="alex")
    metric.update(x, y)
    metric.update(y, x)
    assert metric.compute() == pytest.approx(expected.item(), rel=1e-5)


def test_missing_weights_name_what_and_how():
    with pytest.raises(D2TurbError) as err:
        LPIPS("alex")
    msg = str(err.value)
    assert "AlexNet backbone" in msg and "D2TURB_LPIPS_BACKBONE" in msg and "--lpips-backbone" in msg
    assert "\n" not in msg


def test_wrong_or_corrupt_files_give_one_line_errors(alex_files, tmp_path):
    backbone, lin = alex_files
    vgg_lin = tmp_path / "vgg.pth"
    torch.save(_lin_state("vgg"), vgg_lin)
    with pytest.raises(D2TurbError, match=r"lin1\.model\.1\.weight has shape"):
        LPIPS("alex", weights=vgg_lin, backbone=backbone)
    partial = tmp_path / "partial.pth"
    torch.save({k: v for k, v in _alex_state().items() if "features.10" not in k}, partial)
    with pytest.raises(D2TurbError, match="missing keys.*features.10"):
        LPIPS("alex", weights=lin, backbone=partial)
    corrupt = tmp_path / "corrupt.pth"
    corrupt.write_bytes(b"not a checkpoint")
    with pytest.raises(D2TurbError, match="cannot load"):
        LPIPS("alex", weights=corrupt, backbone=backbone)
    with pytest.raises(D2TurbError, match="unknown LPIPS network"):
        LPIPS("squeeze", weights=lin, backbone=backbone)


def test_vgg_variant_loads_torchvision_keys(tmp_path):
    backbone, lin = tmp_path / "vgg16.safetensors", tmp_path / "vgg.pth"
    save_file(_vgg_state(), str(backbone))
    torch.save(_lin_state("vgg"), lin)
    model = LPIPS("vgg", weights=lin, backbone=backbone)
    assert torch.equal(model.features.features[28].weight, _vgg_state()["features.28.weight"])
    x, y = _images(2, size=32)
    d = model(x, y)
    assert d.shape == (2,) and (d > 0).all()
    assert torch.equal(model(x, x), torch.zeros(2))
    assert torch.equal(model(x, y), d)


def test_feature_extractor_taps_for_perceptual_losses():
    mean_grey = torch.tensor(TORCHVISION_IMAGENET_MEAN).view(1, 3, 1, 1).expand(1, 3, 8, 8)
    assert torch.allclose(imagenet_normalize(mean_grey), torch.zeros(1, 3, 8, 8), atol=1e-6)
    one_std_up = mean_grey + torch.tensor(TORCHVISION_IMAGENET_STD).view(1, 3, 1, 1)
    assert torch.allclose(imagenet_normalize(one_std_up), torch.ones(1, 3, 8, 8), atol=1e-6)
    taps = FeatureExtractor("vgg")(torch.rand(1, 3, 32, 32))
    assert [t.shape[1:] for t in taps] == [(64, 32, 32), (128, 16, 16), (256, 8, 8), (512, 4, 4), (512, 2, 2)]
    taps = FeatureExtractor("alex")(torch.rand(1, 3, 64, 64))
    assert [t.shape[1] for t in taps] == [64, 192, 384, 256, 256] and taps[0].shape[-1] == 15  # (64+4-11)//4+1
