"""Library habits: errors are ValueErrors that keep their cause, no hidden process-wide state, bounded caches."""

import os

import pytest
import torch

import d2turb.eval.musiq as musiq_module
from d2turb.errors import D2TurbError
from d2turb.io import read_image
from d2turb.sim import TurbulenceParams
from d2turb.sim.psf import pca_basis


def test_d2turb_error_is_a_value_error_that_keeps_its_cause(tmp_path):
    assert issubclass(D2TurbError, ValueError)
    with pytest.raises(ValueError, match="aperture_m must be a number") as err:
        TurbulenceParams(aperture_m="wide")
    assert isinstance(err.value.__cause__, ValueError)  # float("wide")
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    with pytest.raises(D2TurbError, match="cannot read image") as err:
        read_image(bad)
    assert err.value.__cause__ is not None


def test_pca_basis_leaves_the_thread_count_as_it_found_it():
    torch.set_num_threads(2)
    psfs = torch.rand(50, 9, 9, generator=torch.Generator().manual_seed(0))
    pca_basis(psfs / psfs.sum(dim=(-2, -1), keepdim=True))
    assert torch.get_num_threads() == 2


def test_depth_anything_does_not_set_hf_hub_offline(tmp_path, monkeypatch):
    pytest.importorskip("transformers")
    from d2turb.depth import DepthAnything

    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    (tmp_path / "config.json").write_text("{}")  # a folder that exists but holds no model
    with pytest.raises(D2TurbError, match="cannot load"):
        DepthAnything(tmp_path)
    assert "HF_HUB_OFFLINE" not in os.environ


@pytest.fixture
def fake_musiq(monkeypatch):
    """MUSIQ replaced by a counter of loads; the model cache is emptied before and after."""
    loads = []

    class Fake:
        def __init__(self, path, device="cpu"):
            loads.append(path.name)

        def __call__(self, image):
            return torch.zeros(image.shape[0])

    musiq_module._cached_model.cache_clear()
    monkeypatch.setattr(musiq_module, "MUSIQ", Fake)
    yield loads
    musiq_module._cached_model.cache_clear()


def test_musiq_model_cache_is_bounded(tmp_path, fake_musiq):
    files = []
    for name in "abc":
        files.append(tmp_path / f"{name}.pth")
        files[-1].write_bytes(b"")
    image = torch.rand(1, 3, 8, 8)
    for path in files + files[-1:]:  # a, b, c, then c again: cached
        musiq_module.musiq(image, weights=path)
    assert fake_musiq == ["a.pth", "b.pth", "c.pth"]
    musiq_module.musiq(image, weights=files[0])  # a was evicted: at most two models stay loaded
    assert fake_musiq == ["a.pth", "b.pth", "c.pth", "a.pth"]
    assert musiq_module._cached_model.cache_info().currsize == 2
