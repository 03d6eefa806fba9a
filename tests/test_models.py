"""D²Turb model family: registry, forward/backward on odd sizes, identity at init, bf16, weights I/O, paper budgets."""

import json

import pytest
import torch
import torch.nn.functional as F

from d2turb.errors import D2TurbError
from d2turb.models import (
    create_backbone,
    create_model,
    list_backbones,
    list_models,
    load_pretrained,
    model_cost,
    parameter_count,
    save_pretrained,
)
from d2turb.models.injection import ASPI

TINY_RESTORMER = {"dim": 8, "num_blocks": [1, 1, 1, 1], "heads": [1, 1, 2, 2], "num_refinement_blocks": 1}
TINY_NAFNET = {"width": 8, "enc_blocks": [1, 1], "middle_blocks": 1, "dec_blocks": [1, 1]}
TINY_RECT = {"width": 8, "mults": [1, 1, 2, 2], "depth": 3}

# tiny configs (id -> (model name, config)); test_every_registered_model_is_covered keeps this in step with the registry
CASES = {
    "restormer": ("restormer", TINY_RESTORMER),
    "nafnet": ("nafnet", TINY_NAFNET),
    "d2turb-restormer-aspi": (
        "d2turb",
        {
            "backbone": "restormer",
            "injection": "aspi",
            "backbone_cfg": TINY_RESTORMER,
            "rectifier_cfg": TINY_RECT,
            "injection_cfg": {"heads": 2},
        },
    ),
    "d2turb-restormer-concat": (
        "d2turb",
        {"backbone": "restormer", "injection": "concat", "backbone_cfg": TINY_RESTORMER, "rectifier_cfg": TINY_RECT},
    ),
    "d2turb-nafnet-none-depth5-resbottleneck": (
        "d2turb",
        {
            "backbone": "nafnet",
            "injection": "none",
            "backbone_cfg": TINY_NAFNET,
            "rectifier_cfg": {"width": 4, "mults": [1, 1, 2, 2, 4, 4], "depth": 5, "residual_bottleneck": True},
        },
    ),
    "d2turb_lite-depth4-normalized": (
        "d2turb_lite",
        {
            "backbone_cfg": TINY_NAFNET,
            "rectifier_cfg": {"width": 8, "mults": [1, 1, 2, 2, 2], "depth": 4, "flow_mode": "normalized"},
        },
    ),
}
D2TURB_CASES = [k for k, (name, _) in CASES.items() if name.startswith("d2turb")]
KEYS = {"deblurred", "restored", "flow", "guide"}


def build(case_id, seed=0):
    torch.manual_seed(seed)
    name, cfg = CASES[case_id]
    return create_model(name, **cfg)


def test_every_registered_model_is_covered():
    from test_baselines import CASES as BASELINE_CASES  # the paper's comparison methods, tested there

    assert {name for name, _ in [*CASES.values(), *BASELINE_CASES.values()]} == set(list_models())
    assert set(list_backbones()) <= set(list_models())  # plain backbones are standalone restorers too


@pytest.mark.parametrize("case_id", CASES)
def test_forward_odd_size(case_id):
    model = build(case_id)
    x = torch.rand(2, 3, 67, 93)
    out = model(x)
    assert set(out) == KEYS and model.config["name"] == CASES[case_id][0]
    for key in ("deblurred", "restored"):
        assert out[key].shape == x.shape and torch.isfinite(out[key]).all()
    assert out["guide"].shape[-2:] == x.shape[-2:] and out["guide"].shape[1] == model.backbone.guide_channels
    if CASES[case_id][0] in ("restormer", "nafnet"):
        assert out["flow"] is None and out["restored"] is out["deblurred"]
    else:
        assert out["flow"].shape == (2, 2, 67, 93)


@pytest.mark.parametrize("size", [(5, 7), (33, 17)])
def test_tiny_inputs_pad_by_replication(size):
    out = build("d2turb-nafnet-none-depth5-resbottleneck")(torch.rand(1, 3, *size))  # 5x7 < 32: replicate padding
    assert out["restored"].shape == (1, 3, *size)


@pytest.mark.parametrize("case_id", CASES)
def test_every_parameter_gets_a_gradient(case_id):
    """Two SGD steps. Zero-initialised parameters (flow head, NAFNet's β/γ) block the gradient of what lies behind
    them on the first step only; on the second every parameter must receive a finite, nonzero gradient."""
    model = build(case_id)
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    gen = torch.Generator().manual_seed(1)
    x, target = torch.rand(2, 1, 3, 27, 35, generator=gen)
    target_flow = torch.randn(1, 2, 27, 35, generator=gen)
    for _ in range(2):
        opt.zero_grad()
        out = model(x)
        loss = F.l1_loss(out["restored"], target) + F.l1_loss(out["deblurred"], target)
        if out["flow"] is not None:
            loss = loss + F.mse_loss(out["flow"], target_flow)
        loss.backward()
        opt.step()
    assert torch.isfinite(loss)
    for name, p in model.named_parameters():
        assert p.grad is not None, name
        assert torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, f"{name} received no gradient"


@pytest.mark.parametrize("case_id", D2TURB_CASES)
def test_untrained_rectifier_is_identity_warp(case_id):
    out = build(case_id)(torch.rand(1, 3, 67, 93))
    assert torch.count_nonzero(out["flow"]) == 0
    torch.testing.assert_close(out["restored"], out["deblurred"], atol=1e-6, rtol=0)


@pytest.mark.parametrize("flow_mode, bias", [("pixel", (2.0, 1.0)), ("normalized", (2.0 / 16, 1.0 / 8))])
def test_flow_is_in_pixels_and_warps_backward(flow_mode, bias):
    """A constant head bias of (2, 1) px (or its grid-unit equivalent on a 17x33 image) must shift content:
    restored[y, x] = deblurred[y + 1, x + 2] (oracle: array slicing)."""
    cfg = dict(CASES["d2turb-restormer-aspi"][1], rectifier_cfg=dict(TINY_RECT, flow_mode=flow_mode))
    model = create_model("d2turb", **cfg)
    with torch.no_grad():
        model.rectifier.flow_head.bias.copy_(torch.tensor(bias))
        out = model(torch.rand(1, 3, 17, 33))
    torch.testing.assert_close(out["flow"][0, 0], torch.full((17, 33), 2.0), atol=1e-5, rtol=0)
    torch.testing.assert_close(out["flow"][0, 1], torch.full((17, 33), 1.0), atol=1e-5, rtol=0)
    torch.testing.assert_close(out["restored"][..., :-1, :-2], out["deblurred"][..., 1:, 2:], atol=1e-5, rtol=0)


@pytest.mark.parametrize("mode", ["cast", "autocast"])
@pytest.mark.parametrize("case_id", CASES)
def test_bf16_forward_close_to_fp32(case_id, mode):
    """bf16 has an 8-bit mantissa (relative step 2^-8 ≈ 0.004): outputs in [0, 1] must agree to 0.03 max, 0.005 mean,
    both with the model cast to bf16 and under CPU autocast."""
    model = build(case_id).eval()
    x = torch.rand(1, 3, 40, 48)
    with torch.no_grad():
        ref = model(x)
        if mode == "cast":
            out = model.to(torch.bfloat16)(x.to(torch.bfloat16))
        else:
            with torch.autocast("cpu", dtype=torch.bfloat16):
                out = model(x)
    for key in ("deblurred", "restored"):
        assert out[key].dtype == (torch.bfloat16 if mode == "cast" else torch.float32)
        diff = (out[key].float() - ref[key]).abs()
        assert diff.max() < 0.03 and diff.mean() < 0.005, (key, diff.max().item(), diff.mean().item())
    if mode == "autocast":  # the convolutions really ran in bf16
        assert not torch.equal(out["deblurred"], ref["deblurred"])


@pytest.mark.parametrize("case_id", ["nafnet", "d2turb-restormer-aspi", "d2turb_lite-depth4-normalized"])
def test_save_load_round_trip(tmp_path, case_id):
    model = build(case_id).eval()
    with torch.no_grad():  # make every tensor distinctive, so a mis-assigned weight would show
        for p in model.parameters():
            p.add_(torch.randn_like(p) * 0.01)
    path = save_pretrained(model, tmp_path / "m.safetensors")
    assert not list(tmp_path.glob(".*tmp*"))  # no temp file left behind
    loaded = load_pretrained(path)
    assert loaded.config == json.loads(json.dumps(model.config)) and type(loaded) is type(model)
    x = torch.rand(1, 3, 37, 45)
    with torch.no_grad():
        a, b = model(x), loaded(x)
    for key in ("deblurred", "restored", "flow", "guide"):
        if a[key] is None:
            assert b[key] is None
        else:
            assert torch.equal(a[key], b[key]), key


def _data_offset(path):
    return 8 + int.from_bytes(path.read_bytes()[:8], "little")  # safetensors: u64 header length, header, data


def test_corrupt_weights_are_refused(tmp_path):
    from safetensors.torch import save_file

    path = save_pretrained(build("nafnet"), tmp_path / "m.safetensors")
    raw = bytearray(path.read_bytes())
    raw[_data_offset(path) + 100] ^= 0xFF  # flip one byte of tensor data
    bad = tmp_path / "flipped.safetensors"
    bad.write_bytes(bytes(raw))
    with pytest.raises(D2TurbError, match=r"flipped\.safetensors: checksum mismatch"):
        load_pretrained(bad)
    truncated = tmp_path / "truncated.safetensors"
    truncated.write_bytes(path.read_bytes()[:-50])
    with pytest.raises(D2TurbError, match=r"truncated\.safetensors: corrupt"):
        load_pretrained(truncated)
    plain = tmp_path / "plain.safetensors"
    save_file({"w": torch.zeros(3)}, str(plain))
    with pytest.raises(D2TurbError, match="not a d2turb weights file"):
        load_pretrained(plain)
    with pytest.raises(D2TurbError, match="not found"):
        load_pretrained(tmp_path / "missing.safetensors")


def test_bad_names_and_inputs_raise_clear_errors():
    with pytest.raises(D2TurbError, match="unknown model 'nope'; available: .*d2turb"):
        create_model("nope")
    with pytest.raises(D2TurbError, match="unknown backbone"):
        create_model("d2turb", backbone="swinir")
    with pytest.raises(D2TurbError, match="unknown injection"):
        create_model("d2turb", injection="film", backbone="nafnet")
    with pytest.raises(D2TurbError, match="bad config"):
        create_backbone("nafnet", widht=8)
    with pytest.raises(D2TurbError, match=r"\(B, 3, H, W\)"):
        build("nafnet")(torch.rand(1, 4, 16, 16))


def test_paper_parameter_budgets():
    """Efficiency table: Restormer 26.13 M, D²Turb + Restormer 31.82 M (within 1 %), counted on the meta device."""
    assert parameter_count("restormer") == pytest.approx(26.13e6, rel=0.01)
    assert parameter_count("d2turb", backbone="restormer", injection="aspi") == pytest.approx(31.82e6, rel=0.01)
    # with Restormer's WithBias LayerNorm (its deraining/deblurring default) the count is 26.13 M to 4 digits
    assert parameter_count("restormer", norm_bias=True) == pytest.approx(26.13e6, abs=0.005e6)


def test_restormer_macs_match_the_published_figure():
    """Restormer's paper reports 140.99 G "FLOPs" at 256²: these are convolution MACs (FlopCounterMode FLOPs / 2,
    attention matmuls excluded). D²Turb's 150.5 G follows the same convention."""
    cost = model_cost("restormer", size=256)
    assert cost["conv_gmacs"] == pytest.approx(140.99, rel=0.001)
    assert cost["gmacs"] > cost["conv_gmacs"]  # the transposed-attention matmuls add ~13.9 G
    assert model_cost("d2turb", size=256)["conv_gmacs"] == pytest.approx(150.5, rel=0.01)


def test_aspi_is_resolution_invariant(astronaut):
    """The same content at 256² and 1024² (4× bicubic upsampling) must give ASPI attention matrices (channels ×
    channels) that agree and attention outputs whose per-channel std over pixels agree within 10 %.
    Features are a fixed random pointwise embedding of the image, so they scale with the content exactly.
    Contrast: unnormalised QKᵀ/√d logits grow with the pixel count (16×), which this design avoids."""
    torch.manual_seed(0)
    aspi = ASPI(16, 24, heads=4).eval()
    with torch.no_grad():
        aspi.temperature.fill_(8.0)  # a sharp, trained-like temperature makes the test stricter
        embed_s, embed_g = torch.nn.Conv2d(3, 16, 1), torch.nn.Conv2d(3, 24, 1)
        big = F.interpolate(astronaut, scale_factor=4, mode="bicubic", align_corners=False).clamp(0, 1)
        (out_s, attn_s), (out_b, attn_b) = (
            aspi.attend(torch.tanh(embed_s(img)), torch.tanh(embed_g(img)), return_attn=True)
            for img in (astronaut, big)
        )
    assert big.shape[-1] == 1024
    assert (attn_s - attn_b).abs().max() < 0.02
    assert attn_s.max() > 1.5 / 4  # not uniform (4 channels per head), so the comparison is meaningful
    ratio = out_b.std(dim=(2, 3)) / out_s.std(dim=(2, 3))
    assert ((ratio - 1).abs() < 0.10).all(), ratio
    with torch.no_grad():  # the naive alternative is not scale-free: logits grow with H·W
        q = aspi.to_q(aspi.norm_q(torch.tanh(embed_s(astronaut)))).flatten(2)
        q_big = aspi.to_q(aspi.norm_q(torch.tanh(embed_s(big)))).flatten(2)
    assert (q_big @ q_big.transpose(1, 2)).abs().mean() / (q @ q.transpose(1, 2)).abs().mean() > 10
