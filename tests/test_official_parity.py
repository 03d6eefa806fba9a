"""Parity with the authors' D²Turb (HertzDot222/D2Turb, commit bbc2844) through ../shared/fixtures/official_d2turb:
their rectifier's outputs computed by their code (oracle), their full state-dict layout (every key and shape).
Skips when ../shared is absent."""

import json
import re
from pathlib import Path

import pytest
import torch

from d2turb.errors import D2TurbError
from d2turb.models import count_parameters, create_model, load_pretrained
from d2turb.models.convert import convert_official_state_dict
from d2turb.models.rectifier import TiltRectifier
from d2turb.models.weights import load_state_dict_strict, read_state_dict

FIXTURE = Path(__file__).resolve().parents[1] / ".." / "shared" / "fixtures" / "official_d2turb"


@pytest.fixture
def fixture_dir() -> Path:
    if not FIXTURE.is_dir():
        pytest.skip(f"fixture folder {FIXTURE} is absent")
    return FIXTURE


def _rectifier_state(fixture_dir):
    from safetensors.torch import load_file

    raw = load_file(str(fixture_dir / "rectifier_weights_fp16.safetensors"))
    converted = convert_official_state_dict({k: v.float() for k, v in raw.items()})
    return {k[len("rectifier.") :]: v for k, v in converted.items()}


@pytest.mark.parametrize("case", ["case0", "case1"])
def test_rectifier_reproduces_the_authors_outputs(fixture_dir, case):
    """Their TiltRectifier's flow and rectified image (their code, float32 CPU) within 1e-4."""
    from safetensors.torch import load_file

    from d2turb.ops.warp import warp

    rect = TiltRectifier(guide_channels=96).eval()
    load_state_dict_strict(rect, _rectifier_state(fixture_dir), "rectifier fixture")
    data = load_file(str(fixture_dir / "rectifier_cases.safetensors"))
    deblurred, guide = data[f"{case}_deblurred"].float(), data[f"{case}_guide"].float()
    with torch.no_grad():
        flow = rect(deblurred, guide)
        rectified = warp(deblurred.double(), flow.double()).float()
    expected_flow = data[f"{case}_pixel_flow"]
    assert expected_flow.abs().mean() > 0.1  # the oracle flow is far from zero, so the comparison is meaningful
    torch.testing.assert_close(flow, expected_flow, atol=1e-4, rtol=0)
    torch.testing.assert_close(rectified, data[f"{case}_rectified"], atol=1e-4, rtol=0)


def _layout(fixture_dir) -> dict:
    return json.loads((fixture_dir / "official_state_dict_layout.json").read_text())


def test_paper_model_has_the_authors_parameter_count(fixture_dir):
    layout = _layout(fixture_dir)
    total = sum(torch.Size(s).numel() for s in layout["keys"].values())
    assert total == layout["total_parameters"] == 31_823_767
    with torch.device("meta"):
        model = create_model("d2turb")
    assert count_parameters(model) == 31_823_767
    backbone = sum(torch.Size(s).numel() for k, s in layout["keys"].items() if k.startswith("restormer."))
    assert count_parameters(model.backbone) == backbone == 26_126_644


@pytest.fixture(scope="module")
def official_random():
    """A random state dict with every key and shape of the authors' layout (made once per module)."""
    if not FIXTURE.is_dir():
        pytest.skip(f"fixture folder {FIXTURE} is absent")
    gen = torch.Generator().manual_seed(0)
    layout = json.loads((FIXTURE / "official_state_dict_layout.json").read_text())["keys"]
    return {k: torch.randn(shape, generator=gen) * 0.02 for k, shape in layout.items()}


def _random_official_checkpoint(official_random) -> dict:
    return dict(official_random)


def test_random_official_checkpoint_converts_and_loads_strictly(official_random, tmp_path):
    state = _random_official_checkpoint(official_random)
    torch.save({"state_dict": {f"module.{k}": v for k, v in state.items()}, "epoch": 3}, tmp_path / "official.pth")
    model = load_pretrained(tmp_path / "official.pth")
    ours = model.state_dict()
    # every tensor arrived, by value, at the place the renaming says (oracle: the file's own tensors)
    pairs = [
        ("backbone.patch_embed.weight", "restormer.embed_conv.weight"),
        ("backbone.latent.7.attn.temperature", "restormer.encoders.3.7.attention.temperature"),
        ("backbone.decoder_level1.3.ffn.dwconv.weight", "restormer.decoders.2.3.feed_forward.conv.weight"),
        ("backbone.down2_3.0.weight", "restormer.downs.1.body.0.weight"),
        ("rectifier.inject.gamma", "rectifier.aspi.gamma"),
        ("rectifier.decode_3.body.0.weight", "rectifier.decode_3.body.0.weight"),
    ]
    for ours_key, their_key in pairs:
        assert torch.equal(ours[ours_key].flatten(), state[their_key].flatten()), ours_key
    assert sorted(float(v.sum()) for v in ours.values()) == pytest.approx(
        sorted(float(v.sum()) for v in state.values())
    )


@pytest.mark.parametrize("nesting", ["plain", "params", "params_ema", "state_dict", "model"])
@pytest.mark.parametrize("prefix", ["", "module."])
def test_checkpoint_nesting_and_prefixes_are_recognised(tmp_path, nesting, prefix):
    state = {"rectifier.aspi.gamma": torch.tensor([0.5]), "restormer.output.weight": torch.ones(3, 96, 3, 3)}
    prefixed = {prefix + k: v for k, v in state.items()}
    torch.save(prefixed if nesting == "plain" else {nesting: prefixed, "iter": 10}, tmp_path / "c.pth")
    read = read_state_dict(tmp_path / "c.pth")
    assert read.keys() == state.keys() and all(torch.equal(read[k], state[k]) for k in state)


def test_params_ema_is_preferred_over_params(tmp_path):
    ema, raw = {"w": torch.ones(2)}, {"w": torch.zeros(2)}
    torch.save({"params": raw, "params_ema": ema}, tmp_path / "both.pth")
    assert torch.equal(read_state_dict(tmp_path / "both.pth")["w"], ema["w"])
    assert torch.equal(read_state_dict(tmp_path / "both.pth", key="params")["w"], raw["w"])
    with pytest.raises(D2TurbError, match="no state dict found under 'nope'"):
        read_state_dict(tmp_path / "both.pth", key="nope")


@pytest.mark.parametrize("key", ["restormer.encoders.1.2.norm1.bias", "rectifier.aspi.query.weight"])
def test_missing_key_is_refused_by_name(official_random, tmp_path, key):
    state = _random_official_checkpoint(official_random)
    del state[key]
    torch.save(state, tmp_path / "missing.pth")
    with pytest.raises(D2TurbError, match="missing: " + re.escape(key) + "$"):
        load_pretrained(tmp_path / "missing.pth")


def test_extra_and_misshaped_keys_are_refused_by_name(official_random, tmp_path):
    state = _random_official_checkpoint(official_random)
    state["rectifier.aspi.temperature"] = torch.ones(1)
    torch.save(state, tmp_path / "extra.pth")
    with pytest.raises(D2TurbError, match=r"unexpected: rectifier\.aspi\.temperature$"):
        load_pretrained(tmp_path / "extra.pth")
    del state["rectifier.aspi.temperature"]
    state["rectifier.down_3.body.0.bias"] = torch.zeros(128)
    torch.save(state, tmp_path / "shape.pth")
    with pytest.raises(
        D2TurbError, match=r"mis-shaped \(file vs model\): rectifier\.down_3\.body\.0\.bias \(128,\) vs \(256,\)"
    ):
        load_pretrained(tmp_path / "shape.pth")


def test_nonfinite_weights_are_refused_by_name(official_random, tmp_path):
    state = _random_official_checkpoint(official_random)
    for key, index, value in [("restormer.output.weight", (0, 0, 0, 0), "nan"), ("rectifier.flow_head.bias", 1, "inf")]:
        state[key] = state[key].clone()  # the module-scoped original stays finite
        state[key][index] = float(value)
    torch.save(state, tmp_path / "nan.pth")
    with pytest.raises(D2TurbError, match=r"NaN/Inf\) in rectifier\.flow_head\.bias, restormer\.output\.weight$"):
        load_pretrained(tmp_path / "nan.pth")
