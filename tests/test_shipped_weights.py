"""The shipped restoration model as the default: the registry in models/hub.py (RECOMMENDED_WEIGHTS,
shipped_weights, recommended_weights), `d2turb restore` and Restorer() without weights, `d2turb models` and the demo.
The package's resources folder is patched to a temp folder holding a tiny model; nothing here depends on the real
shipped file."""

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import d2turb.models.hub as hub
from d2turb.cli import main
from d2turb.errors import D2TurbError
from d2turb.io import read_image, write_image
from d2turb.models import create_model, save_pretrained
from d2turb.models.weights import weights_info


@pytest.fixture
def shipped(tmp_path, monkeypatch):
    """The package's resources/weights, moved to an empty temp folder (user folders emptied too)."""
    package = tmp_path / "package"
    folder = package / "resources" / "weights"
    folder.mkdir(parents=True)
    monkeypatch.setattr(hub, "resources", SimpleNamespace(files=lambda name: package))
    monkeypatch.setenv("D2TURB_WEIGHTS_DIR", str(tmp_path / "user"))
    monkeypatch.setenv("D2TURB_CACHE_DIR", str(tmp_path / "cache"))
    return folder


def tiny_nafnet(seed: int = 0):
    """A tiny plain NAFNet (no rectifier) whose output differs visibly from its input."""
    torch.manual_seed(seed)
    model = create_model("nafnet", width=8, enc_blocks=[1, 1], dec_blocks=[1, 1], middle_blocks=1).eval()
    torch.nn.init.normal_(model.backbone.ending.weight, std=0.05)
    return model


@pytest.fixture
def recommended(shipped):
    model = tiny_nafnet()
    save_pretrained(model, shipped / f"{hub.RECOMMENDED_WEIGHTS}.safetensors")
    return model


@pytest.fixture
def image_png(tmp_path):
    rng = np.random.default_rng(0)
    path = tmp_path / "in.png"
    write_image(path, torch.from_numpy(rng.random((3, 40, 56), dtype=np.float32)))
    return path


def test_shipped_weights_lists_the_package_folder_recommended_first(shipped):
    assert hub.shipped_weights() == []
    for name in ("zeta", "alpha", hub.RECOMMENDED_WEIGHTS, "bad name"):
        (shipped / f"{name}.safetensors").write_bytes(b"")
    (shipped / "notes.txt").write_text("not weights")
    assert hub.shipped_weights() == [hub.RECOMMENDED_WEIGHTS, "alpha", "zeta"]
    assert hub.recommended_weights() == shipped / f"{hub.RECOMMENDED_WEIGHTS}.safetensors"


def test_recommended_weights_only_from_the_package(shipped, tmp_path):
    user = tmp_path / "user"
    user.mkdir()
    save_pretrained(tiny_nafnet(), user / f"{hub.RECOMMENDED_WEIGHTS}.safetensors")  # same name, not shipped
    with pytest.raises(D2TurbError, match="no restoration model is shipped") as err:
        hub.recommended_weights()
    assert str(shipped) in str(err.value) and "--weights" in str(err.value)


def test_weights_info_reads_model_and_parameter_count(shipped, recommended):
    info = weights_info(shipped / f"{hub.RECOMMENDED_WEIGHTS}.safetensors")
    assert info["model"] == "nafnet"
    assert info["params"] == sum(t.numel() for t in recommended.state_dict().values())
    bad = shipped / "bad.safetensors"
    bad.write_bytes(b"garbage")
    with pytest.raises(D2TurbError, match="corrupt weights file"):
        weights_info(bad)


def test_restore_without_weights_uses_the_recommended_model(recommended, image_png, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["restore", str(image_png), "--out", str(out)]) == 0
    captured = capsys.readouterr()
    named = [line for line in captured.err.splitlines() if hub.RECOMMENDED_WEIGHTS in line]
    assert len(named) == 1 and "shipped" in named[0]
    x = read_image(image_png)
    with torch.no_grad():  # oracle: the model itself on the whole image (smaller than one tile)
        expected = recommended(x[None])["restored"][0].clamp(0, 1)
    got = read_image(out / "in_restored.png")
    assert (got - expected).abs().max() <= 0.5 / 255 + 1e-6
    assert (got - x).abs().mean() > 0.01  # not the identity


def test_restore_without_any_shipped_model_is_one_error_line(shipped, image_png, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["restore", str(image_png), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "no restoration model is shipped" in err[0]
    assert not out.exists() or not any(out.iterdir())


def test_restorer_without_weights(recommended, shipped, capsys):
    from d2turb.restore import Restorer

    restorer = Restorer()
    assert restorer.name == hub.RECOMMENDED_WEIGHTS
    assert capsys.readouterr().err.count(hub.RECOMMENDED_WEIGHTS) == 1
    x = torch.rand(3, 24, 32, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        expected = recommended(x[None])["restored"][0].clamp(0, 1)
    assert torch.allclose(restorer.restore(x), expected, atol=1e-5)
    (shipped / f"{hub.RECOMMENDED_WEIGHTS}.safetensors").unlink()
    with pytest.raises(D2TurbError, match="no restoration model is shipped"):
        Restorer()


def test_models_marks_the_shipped_weights(recommended, shipped, capsys):
    save_pretrained(tiny_nafnet(1), shipped / "other-small.safetensors")
    assert main(["models"]) == 0
    lines = capsys.readouterr().out.splitlines()
    params = sum(t.numel() for t in recommended.state_dict().values())
    marked = [line for line in lines if line.startswith("* ")]
    assert len(marked) == 1 and marked[0].split()[1] == hub.RECOMMENDED_WEIGHTS and "model nafnet" in marked[0]
    assert f"{params / 1e6:.2f} M params" in marked[0]
    assert any(line.split()[:1] == ["other-small"] for line in lines)
    assert main(["models", "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)["shipped_weights"]
    assert [(w["name"], w["recommended"], w["params"]) for w in listed] == [
        (hub.RECOMMENDED_WEIGHTS, True, params),
        ("other-small", False, params),
    ]


def test_models_says_when_nothing_is_shipped(shipped, capsys):
    assert main(["models"]) == 0
    assert "none in this installation" in capsys.readouterr().out


def test_demo_restores_with_the_recommended_model(recommended, tmp_path, capsys, monkeypatch):
    from d2turb.commands import demo

    monkeypatch.setattr(demo, "CLIP_FRAMES", 4)  # the full demo with the real model: tests/test_demo.py
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"single-frame model {hub.RECOMMENDED_WEIGHTS}" in printed
    meta = json.loads((out / "demo_meta.json").read_text())["restoration"]
    assert meta["weights"] == hub.RECOMMENDED_WEIGHTS
    table = meta["table"]
    assert sorted(table) == ["medium", "strong", "weak"] and "epe_px" not in table["weak"]  # no rectifier
    # the table's restored PSNR is that of the written PNGs against the clean images (numpy recomputation)
    from d2turb.data.samples import sample_images

    clean = sample_images()
    values = []
    for n in clean:
        mse = np.mean((read_image(out / f"{n}_strong_restored.png").numpy() - clean[n].numpy()).astype(np.float64) ** 2)
        values.append(10 * np.log10(1.0 / mse))
    assert table["strong"]["psnr_restored"] == pytest.approx(np.mean(values), abs=1e-3)


def test_demo_without_a_shipped_model_still_simulates(shipped, tmp_path, capsys, monkeypatch):
    from d2turb.commands import demo

    monkeypatch.setattr(demo, "CLIP_FRAMES", 4)
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out)]) == 0
    assert "single-frame restoration skipped" in capsys.readouterr().out
    assert (out / "demo.png").is_file() and not list(out.glob("*_restored.png"))


def test_the_page_preselects_the_recommended_shipped_weights(shipped, tmp_path):
    from d2turb.app import core

    for name in ("aaa-other", hub.RECOMMENDED_WEIGHTS):
        save_pretrained(tiny_nafnet(), shipped / f"{name}.safetensors")
    choices = core.weights_choices()
    assert [n for n, _ in choices] == ["input", "aaa-other", hub.RECOMMENDED_WEIGHTS]  # resolve_weights' order
    assert core.default_weights(choices) == hub.RECOMMENDED_WEIGHTS
    (shipped / f"{hub.RECOMMENDED_WEIGHTS}.safetensors").unlink()
    assert core.default_weights(core.weights_choices()) == "aaa-other"  # another shipped one
