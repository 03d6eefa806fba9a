"""D²Turb model family: registry, forward/backward on odd sizes, identity at init, bf16, weights I/O, paper budgets."""

import json
import warnings

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
    model_output,
    parameter_count,
    save_pretrained,
)
from d2turb.models.injection import ASPI, CosineASPI

TINY_RESTORMER = {"dim": 8, "num_blocks": [1, 1, 1, 1], "heads": [1, 1, 2, 2], "num_refinement_blocks": 1}
TINY_NAFNET = {"width": 8, "enc_blocks": [1, 1], "middle_blocks": 1, "dec_blocks": [1, 1]}
TINY_RECT = {"widths": [8, 8, 16, 16]}  # the authors' rectifier, 3 levels
TINY_UNET = {"width": 8, "mults": [1, 1, 2, 2], "depth": 3}

# tiny configs (id -> (model name, config)); test_every_registered_model_is_covered keeps this in step with the registry
CASES = {
    "restormer": ("restormer", TINY_RESTORMER),
    "nafnet": ("nafnet", TINY_NAFNET),
    "d2turb-restormer-aspi": (
        "d2turb",
        {"backbone": "restormer", "injection": "aspi", "backbone_cfg": TINY_RESTORMER, "rectifier_cfg": TINY_RECT},
    ),
    "d2turb-restormer-concat": (
        "d2turb",
        {"backbone": "restormer", "injection": "concat", "backbone_cfg": TINY_RESTORMER, "rectifier_cfg": TINY_RECT},
    ),
    "d2turb-nafnet-none-5levels": (
        "d2turb",
        {"backbone": "nafnet", "injection": "none", "backbone_cfg": TINY_NAFNET, "rectifier_cfg": {"widths": [4] * 6}},
    ),
    "d2turb-restormer-aspi_cosine-unet": (
        "d2turb",
        {
            "backbone": "restormer",
            "injection": "aspi_cosine",
            "rectifier": "unet",
            "backbone_cfg": TINY_RESTORMER,
            "rectifier_cfg": TINY_UNET,
            "injection_cfg": {"heads": 2},
        },
    ),
    "d2turb-nafnet-none-unet-depth5-resbottleneck": (
        "d2turb",
        {
            "backbone": "nafnet",
            "injection": "none",
            "rectifier": "unet",
            "backbone_cfg": TINY_NAFNET,
            "rectifier_cfg": {"width": 4, "mults": [1, 1, 2, 2, 4, 4], "depth": 5, "residual_bottleneck": True},
        },
    ),
    "d2turb_small": ("d2turb_small", {"backbone_cfg": TINY_NAFNET, "rectifier_cfg": {"widths": [8, 8, 16, 16]}}),
    "d2turb_lite-depth4-normalized": (
        "d2turb_lite",
        {
            "backbone_cfg": TINY_NAFNET,
            "rectifier_cfg": {"width": 8, "mults": [1, 1, 2, 2, 2], "depth": 4, "flow_mode": "normalized"},
        },
    ),
}
D2TURB_CASES = [k for k, (name, _) in CASES.items() if name.startswith("d2turb")]
KEYS = {"deblurred", "restored", "bwd_flow_px", "guide"}  # one key per tensor


def build(case_id, seed=0):
    torch.manual_seed(seed)
    name, cfg = CASES[case_id]
    return create_model(name, **cfg)


def test_every_registered_model_is_covered():
    from test_baselines import CASES as BASELINE_CASES  # the paper's comparison methods, tested there

    assert {name for name, _ in [*CASES.values(), *BASELINE_CASES.values()]} == set(list_models())
    assert set(list_backbones()) <= set(list_models())  # plain backbones are standalone restorers too


def _bilinear_oracle(image: torch.Tensor, flow: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 9 by hand: out(x) = image(x + flow(x)), bilinear from the four neighbours (float64, no grid_sample), and
    where the sample point lies inside the image (there the model's padded canvas and the cropped image agree)."""
    image, flow = image.double(), flow.double()
    b, c, h, w = image.shape
    xs = torch.arange(w, dtype=torch.float64) + flow[:, 0]
    ys = torch.arange(h, dtype=torch.float64)[:, None] + flow[:, 1]
    inside = (xs >= 0) & (xs <= w - 1) & (ys >= 0) & (ys <= h - 1)
    x0 = xs.floor().clamp(0, w - 2).long()
    y0 = ys.floor().clamp(0, h - 2).long()
    fx, fy = (xs - x0).clamp(0, 1)[:, None], (ys - y0).clamp(0, 1)[:, None]

    def at(yi, xi):
        return image.flatten(2).gather(2, (yi * w + xi).flatten(1)[:, None].expand(b, c, -1)).view(b, c, h, w)

    top = at(y0, x0) * (1 - fx) + at(y0, x0 + 1) * fx
    bottom = at(y0 + 1, x0) * (1 - fx) + at(y0 + 1, x0 + 1) * fx
    return top * (1 - fy) + bottom * fy, inside[:, None].expand(b, c, h, w)


@pytest.mark.parametrize("case_id", CASES)
def test_forward_odd_size(case_id):
    model = build(case_id)
    if hasattr(model, "rectifier"):  # a flow that moves pixels (the flow head starts at zero)
        torch.nn.init.normal_(model.rectifier.flow_head.weight, std=2.0)
    x = torch.rand(2, 3, 67, 93)
    with torch.no_grad():
        out = model(x)
    assert set(out) == KEYS and model.config["name"] == CASES[case_id][0]
    for key in ("deblurred", "restored"):
        assert out[key].shape == x.shape and torch.isfinite(out[key]).all()
    assert out["guide"].shape[-2:] == x.shape[-2:] and out["guide"].shape[1] == model.backbone.guide_channels
    if CASES[case_id][0] in ("restormer", "nafnet"):
        assert out["bwd_flow_px"] is None and out["restored"] is out["deblurred"]
    else:
        assert out["bwd_flow_px"].shape == (2, 2, 67, 93)
        with pytest.warns(DeprecationWarning, match="bwd_flow_px"):  # the deprecated name: still read, warning
            assert out["flow"] is out["bwd_flow_px"]
        assert "pixel_flow" not in out  # the authors' name: an alias no more
        expected, inside = _bilinear_oracle(out["deblurred"], out["bwd_flow_px"])
        assert out["bwd_flow_px"].abs().amax() > 0.5 and inside.float().mean() > 0.1
        assert torch.allclose(out["restored"].double()[inside], expected[inside], atol=1e-5)


@pytest.mark.parametrize("size", [(5, 7), (33, 17)])
def test_tiny_inputs_pad_by_replication(size):
    out = build("d2turb-nafnet-none-unet-depth5-resbottleneck")(torch.rand(1, 3, *size))  # 5x7 < 32: replicate padding
    assert out["restored"].shape == (1, 3, *size)


@pytest.mark.parametrize("case_id", CASES)
def test_every_parameter_gets_a_gradient(case_id):
    """Zero-initialised parameters (flow head, NAFNet's β/γ, the authors' ASPI γ) block the gradient of what lies
    behind them until they have moved: the flow head moves on step 1 and the authors' ASPI γ on step 2, so on the
    last of two SGD steps (three with the authors' ASPI) every parameter must receive a finite, nonzero gradient."""
    model = build(case_id)
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    gen = torch.Generator().manual_seed(1)
    x, target = torch.rand(2, 1, 3, 27, 35, generator=gen)
    target_flow = torch.randn(1, 2, 27, 35, generator=gen)
    for _ in range(3 if any(isinstance(m, ASPI) for m in model.modules()) else 2):
        opt.zero_grad()
        out = model(x)
        loss = F.l1_loss(out["restored"], target) + F.l1_loss(out["deblurred"], target)
        if out["bwd_flow_px"] is not None:
            loss = loss + F.mse_loss(out["bwd_flow_px"], target_flow)
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
    assert torch.count_nonzero(out["bwd_flow_px"]) == 0
    torch.testing.assert_close(out["restored"], out["deblurred"], atol=1e-6, rtol=0)


@pytest.mark.parametrize(
    "rectifier, rect_cfg, bias",
    [
        ("authors", TINY_RECT, (2.0, 1.0)),
        ("unet", TINY_UNET, (2.0, 1.0)),
        ("unet", dict(TINY_UNET, flow_mode="normalized"), (2.0 / 16, 1.0 / 8)),
    ],
)
def test_flow_is_in_pixels_and_warps_backward(rectifier, rect_cfg, bias):
    """A constant head bias of (2, 1) px (or its grid-unit equivalent on a 17x33 image) must shift content:
    restored[y, x] = deblurred[y + 1, x + 2] (oracle: array slicing)."""
    cfg = dict(CASES["d2turb-restormer-aspi"][1], rectifier=rectifier, rectifier_cfg=rect_cfg)
    model = create_model("d2turb", **cfg)
    with torch.no_grad():
        model.rectifier.flow_head.bias.copy_(torch.tensor(bias))
        out = model(torch.rand(1, 3, 17, 33))
    torch.testing.assert_close(out["bwd_flow_px"][0, 0], torch.full((17, 33), 2.0), atol=1e-5, rtol=0)
    torch.testing.assert_close(out["bwd_flow_px"][0, 1], torch.full((17, 33), 1.0), atol=1e-5, rtol=0)
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
    for key in ("deblurred", "restored", "bwd_flow_px", "guide"):
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
    with pytest.raises(D2TurbError, match=r"plain\.safetensors: not weights of model 'd2turb' \(none of its 1 keys"):
        load_pretrained(plain)
    with pytest.raises(D2TurbError, match="not found"):
        load_pretrained(tmp_path / "missing.safetensors")


def test_files_written_before_format_2_load_with_their_old_defaults(tmp_path):
    """A file from before the authors' architecture became the default (no ``d2turb_format`` in its metadata): its
    config {"backbone": "restormer", "injection": "aspi"} then meant Restormer's bias-free LayerNorm, the U-Net
    rectifier and the cosine ASPI, and it must load as exactly that model."""
    from safetensors.torch import save_file

    from d2turb.models.weights import tensors_sha256

    old = {"backbone": "restormer", "injection": "aspi", "backbone_cfg": TINY_RESTORMER, "rectifier_cfg": TINY_UNET}
    then = dict(old, injection="aspi_cosine", rectifier="unet", backbone_cfg=dict(TINY_RESTORMER, norm_bias=False))
    torch.manual_seed(0)
    model = create_model("d2turb", **then).eval()
    tensors = {k: v.contiguous() for k, v in model.state_dict().items()}
    meta = {"d2turb_config": json.dumps({"name": "d2turb", **old}), "d2turb_sha256": tensors_sha256(tensors)}
    save_file(tensors, str(tmp_path / "old.safetensors"), metadata=meta)
    loaded = load_pretrained(tmp_path / "old.safetensors")
    assert loaded.config == json.loads(json.dumps({"name": "d2turb", **then}))
    x = torch.rand(1, 3, 32, 32)
    with torch.no_grad():
        assert torch.equal(loaded(x)["restored"], model(x)["restored"])


def test_bad_names_and_inputs_raise_clear_errors():
    with pytest.raises(D2TurbError, match="unknown model 'nope'; available: .*d2turb"):
        create_model("nope")
    with pytest.raises(D2TurbError, match="unknown backbone"):
        create_model("d2turb", backbone="swinir")
    with pytest.raises(D2TurbError, match="unknown injection"):
        create_model("d2turb", injection="film", backbone="nafnet")
    with pytest.raises(D2TurbError, match="unknown rectifier 'raft'; available: authors, unet"):
        create_model("d2turb", rectifier="raft", backbone="nafnet")
    with pytest.raises(D2TurbError, match="bad rectifier/injection config.*widths"):
        create_model("d2turb", backbone="nafnet", rectifier_cfg={"widths": [32]})
    with pytest.raises(D2TurbError, match="bad rectifier/injection config"):
        create_model("d2turb", backbone="nafnet", rectifier_cfg={"width": 8})  # a unet keyword for the authors' one
    with pytest.raises(D2TurbError, match="bad config"):
        create_backbone("nafnet", widht=8)
    with pytest.raises(D2TurbError, match=r"\(B, 3, H, W\)"):
        build("nafnet")(torch.rand(1, 4, 16, 16))


def test_paper_parameter_budgets():
    """Efficiency table: Restormer 26.13 M, D²Turb 31.82 M; exactly the authors' model (26,126,644 and 31,823,767
    parameters in their released state dict)."""
    assert parameter_count("restormer") == 26_126_644
    assert parameter_count("d2turb") == 31_823_767
    assert parameter_count("d2turb", backbone="restormer", injection="aspi", rectifier="authors") == 31_823_767


def test_restormer_macs_match_the_published_figure():
    """Restormer's paper reports 140.99 G "FLOPs" at 256²: these are convolution MACs (FlopCounterMode FLOPs / 2,
    attention matmuls excluded). D²Turb's 150.5 G follows the same convention."""
    cost = model_cost("restormer", size=256)
    assert cost["conv_gmacs"] == pytest.approx(140.99, rel=0.001)
    assert cost["gmacs"] > cost["conv_gmacs"]  # the transposed-attention matmuls add ~13.9 G
    assert model_cost("d2turb", size=256)["conv_gmacs"] == pytest.approx(150.5, rel=0.01)


def _attention_reference(q, k, temperature, heads):
    """Cosine channel attention, written out in float64: each channel's q and k are divided by their L2 norm over
    the pixels, logits = q̂·k̂ · τ (per head), softmax over the key channels."""
    b, c = q.shape[:2]
    q, k = (t.double().reshape(b, heads, c // heads, -1) for t in (q, k))
    q = q / q.pow(2).sum(-1, keepdim=True).sqrt()
    k = k / k.pow(2).sum(-1, keepdim=True).sqrt()
    logits = torch.einsum("bhip,bhjp->bhij", q, k) * temperature.double().reshape(1, heads, 1, 1)
    return logits.softmax(-1)


def test_cosine_aspi_is_resolution_invariant(astronaut):
    """Variant aspi_cosine. The same content at 128² and 512² (4× bicubic upsampling) must give attention matrices
    (channels × channels) that agree (0.005) and attention outputs whose per-channel std over pixels agree (2 %).
    Features are a fixed random pointwise embedding of the image, so they scale with the content exactly. The
    attention equals a reference that normalises q and k over pixels, and is neither uniform nor saturated (a
    saturated softmax would agree at any resolution). (At 256² and 1024² the attention matrices agreed to 0.0010
    and the stds to 0.16 %, as here to 0.0003 and 0.14 %; 1024² took 0.6 GB.)"""
    torch.manual_seed(0)
    heads = 4
    aspi = CosineASPI(16, 24, heads=heads).eval()
    small = astronaut[..., 64:192, 64:192]  # the face, 128²
    with torch.no_grad():
        aspi.temperature.copy_(torch.tensor([2.0, 3.0, 2.5, 1.5]).reshape(heads, 1, 1))  # sharp, but not saturated
        embed_s, embed_g = torch.nn.Conv2d(3, 16, 1), torch.nn.Conv2d(3, 24, 1)
        big = F.interpolate(small, scale_factor=4, mode="bicubic", align_corners=False).clamp(0, 1)
        feats = [(torch.tanh(embed_s(img)), torch.tanh(embed_g(img))) for img in (small, big)]
        (out_s, attn_s), (out_b, attn_b) = (aspi.attend(s, g, return_attn=True) for s, g in feats)
        shallow, guide = feats[0]
        q = aspi.to_q(aspi.norm_q(shallow))
        k = aspi.to_kv(aspi.norm_kv(guide)).chunk(2, dim=1)[0]
    assert big.shape[-1] == 512
    reference = _attention_reference(q, k, aspi.temperature, heads)  # float32 sums over 16k pixels: ~1e-5 round-off
    torch.testing.assert_close(attn_s.double(), reference, atol=2e-4, rtol=0)
    assert attn_s.max() > 1.5 / 4  # not uniform (4 channels per head), so the comparison is meaningful
    assert attn_s.max() < 0.9 and attn_b.max() < 0.9  # not saturated: every row still mixes several channels
    assert (attn_s - attn_b).abs().max() < 0.005
    ratio = out_b.std(dim=(2, 3)) / out_s.std(dim=(2, 3))
    assert ((ratio - 1).abs() < 0.02).all(), ratio


def test_authors_aspi_is_eq10_with_sdpa_channel_attention():
    """The authors' ASPI: F_fused = F_shallow + γ · SDPA(Q, K, V) over (B, C, H·W), one head (oracle:
    torch's scaled_dot_product_attention, whose default scale is 1/√(H·W) here); γ = 0 gives F_shallow exactly."""
    torch.manual_seed(0)
    aspi = ASPI(8, 12)
    shallow, guide = torch.randn(2, 8, 9, 11), torch.randn(2, 12, 9, 11)
    with torch.no_grad():
        assert aspi.gamma.item() == 0.0
        assert torch.equal(aspi(shallow, guide), shallow)  # γ = 0 (initialisation): F_fused = F_shallow exactly
        aspi.gamma.fill_(0.7)
        fused = aspi(shallow, guide)
        q = F.conv2d(shallow, aspi.query.weight).flatten(2)
        k, v = (F.conv2d(guide, conv.weight).flatten(2) for conv in (aspi.key, aspi.value))
    expected = shallow + 0.7 * F.scaled_dot_product_attention(q, k, v).reshape(2, 8, 9, 11)
    torch.testing.assert_close(fused, expected, atol=1e-5, rtol=0)
    assert (fused - shallow).abs().mean() > 0.05  # the attention term is not negligible


def test_authors_aspi_sharpens_with_resolution(astronaut):
    """The authors' scaling 1/√(H·W) is not resolution-free: for the same content at 4× the side (16× the pixels)
    the inner products grow 16× and the scale shrinks 4×, so logit differences grow 4× (oracle: that arithmetic;
    log-softmax differences are logit differences). The content is 128² and 512²; features of amplitude 0.42 give
    the logits that 0.3 gave at 256² and 1024² (logits scale as amplitude²·√(H·W): 0.42²·128 ≈ 0.3²·256)."""
    torch.manual_seed(0)
    aspi = ASPI(16, 24)
    small = astronaut[..., 64:192, 64:192]  # the face, 128²
    with torch.no_grad():
        embed_s, embed_g = torch.nn.Conv2d(3, 16, 1), torch.nn.Conv2d(3, 24, 1)
        big = F.interpolate(small, scale_factor=4, mode="bicubic", align_corners=False).clamp(0, 1)
        attn_s, attn_b = (
            aspi.attend(0.42 * torch.tanh(embed_s(img)), 0.42 * torch.tanh(embed_g(img)), return_attn=True)[1]
            for img in (small, big)
        )
    assert attn_b.max() < 0.99  # no probability underflows to 0, so log-softmax differences are exact
    gap_s, gap_b = (a.log().amax(-1) - a.log().amin(-1) for a in (attn_s, attn_b))
    assert gap_s.min() > 0.1  # the small-image logits are not flat, so the ratio is meaningful
    torch.testing.assert_close(gap_b / gap_s, torch.full_like(gap_s, 4.0), atol=0.02, rtol=0)
    assert attn_b.amax(-1).mean() > attn_s.amax(-1).mean() + 0.1  # sharper at full size


@pytest.mark.parametrize("case_id, output", [("restormer", "output"), ("nafnet", "ending")])
def test_backbone_global_residual(case_id, output):
    """Î_tilt = Conv3×3(F_guide) + I_turb (the backbones' global residual), checked by value; with the output conv
    zeroed the backbone is exactly the identity."""
    backbone = build(case_id).backbone.eval()
    image = torch.rand(1, 3, 32, 40)
    conv = getattr(backbone, output)
    with torch.no_grad():
        deblurred, guide = backbone(image)
        torch.testing.assert_close(deblurred, F.conv2d(guide, conv.weight, conv.bias, padding=1) + image)
        conv.weight.zero_()
        if conv.bias is not None:
            conv.bias.zero_()
        assert torch.equal(backbone(image)[0], image)


@pytest.mark.parametrize("size, mode", [((40, 50), "reflect"), ((20, 70), "reflect"), ((9, 40), "replicate")])
def test_whole_pipeline_runs_padded_to_32(size, mode):
    """The authors' rule: the input is padded bottom/right to a multiple of 32 (reflect when each pad is smaller than
    its side, else replicate); backbone, rectifier and the warp run on the padded image and the outputs are cropped.
    Oracle: the model on the input padded by hand (a multiple of 32 already), cropped. A nonzero flow makes the warp
    sample across the crop border, where warping the cropped image (border clamp) would differ."""
    model = build("d2turb-restormer-aspi").eval()
    with torch.no_grad():
        model.rectifier.flow_head.bias.copy_(torch.tensor([2.5, 1.5]))
        model.rectifier.inject.gamma.fill_(0.5)
        x = torch.rand(1, 3, *size)
        h, w = size
        padded = F.pad(x, (0, (-w) % 32, 0, (-h) % 32), mode=mode)
        out, ref = model(x), model(padded)
    for key in ("deblurred", "restored", "bwd_flow_px", "guide"):
        torch.testing.assert_close(out[key], ref[key][..., :h, :w], atol=1e-6, rtol=0)


def test_model_output_one_key_per_tensor_old_names_warn_once():
    flow = torch.zeros(1, 2, 4, 4)
    out = model_output(torch.zeros(1, 3, 4, 4), torch.ones(1, 3, 4, 4), flow)
    assert set(out) == KEYS and len(dict(out)) == 4 and "flow" in out and "pixel_flow" not in out
    with pytest.warns(DeprecationWarning, match=r"model output\['flow'\] is deprecated"):
        assert out.get("flow") is flow
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert out["flow"] is flow and out["bwd_flow_px"] is flow  # once per process
        assert out.get("missing", 3) == 3
    with pytest.raises(KeyError):
        out["missing"]
    from torch.utils._pytree import tree_flatten, tree_map

    leaves, _ = tree_flatten(out)  # flattens like a dict (DDP finds the tensors), and maps back to its own type
    assert sum(isinstance(t, torch.Tensor) for t in leaves) == 3 and type(tree_map(lambda t: t, out)) is type(out)
