"""The paper's comparison methods (AT-Net, TurbNet, TMT, FocalNet, AdaIR) and the D²Turb presets with the FocalNet and
AdaIR backbones: output contract, gradients in every parameter at an odd size with each method's own objective,
published parameter counts, the published building blocks against independent formulas, train + restore via the CLI."""

import json
from pathlib import Path

import pytest
import torch
import yaml

from d2turb.cli import main
from d2turb.models import create_model, list_models, parameter_count
from d2turb.models.adair import _box
from d2turb.models.complexity import PAPER_EFFICIENCY
from d2turb.models.focalnet import fft_l1
from d2turb.models.injection import ASPI
from d2turb.models.rectifier import TiltRectifier
from d2turb.models.restormer import Restormer
from d2turb.models.tmt import ShuffleAttention, published_parameter_count
from d2turb.train import build_loss, load_config

REPO = Path(__file__).resolve().parents[1]
TINY_RESTORMER = {"dim": 8, "num_blocks": [1, 1, 1, 1], "heads": [1, 1, 2, 2], "num_refinement_blocks": 1}
TINY_FOCALNET = {"base_channels": 8, "num_res": 1}
TINY_ADAIR = {**TINY_RESTORMER, "freq_div": 4}  # freq_div 4: non-empty low-frequency masks at these tiny sizes
TINY_RECT = {"widths": [8, 8, 16, 16]}  # the authors' rectifier, 3 levels (its ASPI has no options)
CASES = {
    "atnet": ("atnet", {"width": 8, "cardinality": 4, "scale": 3, "mc_samples": 2}),
    "turbnet": ("turbnet", TINY_RESTORMER),
    "tmt": ("tmt", {"dim": 8, "num_blocks": [1, 1, 1, 1], "heads": [1, 1, 2, 2], "num_refinement_blocks": 1}),
    "focalnet": ("focalnet", TINY_FOCALNET),
    "adair": ("adair", TINY_ADAIR),
    "d2turb_focalnet": (
        "d2turb_focalnet",
        {"backbone_cfg": TINY_FOCALNET, "rectifier_cfg": TINY_RECT},
    ),
    "d2turb_adair": (
        "d2turb_adair",
        {"backbone_cfg": TINY_ADAIR, "rectifier_cfg": TINY_RECT},
    ),
}
KEYS = {"deblurred", "restored", "bwd_flow_px", "guide"}
# each method's own training terms (extra_loss), logged next to the project's photometric / multi-stage terms
OWN_TERMS = {
    "atnet": {"half", "angular", "grad_angular", "prior"},
    "turbnet": {"redegrade"},
    "tmt": set(),
    "focalnet": {"multiscale", "fft"},
    "adair": set(),
    "d2turb_focalnet": {"multiscale", "fft"},
    "d2turb_adair": set(),
}


def build(case_id, seed=0):
    torch.manual_seed(seed)
    name, cfg = CASES[case_id]
    return create_model(name, **cfg)


def fake_batch(h=67, w=93, seed=1):
    g = torch.Generator().manual_seed(seed)
    turb, gt, tilt = torch.rand(3, 2, 3, h, w, generator=g)
    return {"turb": turb, "gt": gt, "tilt": tilt, "bwd_flow_px": torch.randn(2, 2, h, w, generator=g)}


def test_paper_rows_are_registered():
    assert {name for _, name, _, _, _ in PAPER_EFFICIENCY} <= set(list_models())
    assert {name for name, _ in CASES.values()} <= set(list_models())


@pytest.mark.parametrize("case_id", CASES)
def test_forward_backward_every_parameter_gets_a_gradient(case_id):
    """SGD steps at 67×93 on the project's objective plus the method's own terms (build_loss with the model's
    extra_loss). Zero-initialised parameters block what lies behind them until they have moved: AdaIR's gains and
    D²Turb's flow head on step 1, the authors' ASPI γ on step 2; so on the last of two steps (three with the authors'
    ASPI) every parameter must receive a finite, nonzero gradient."""
    model = build(case_id)
    loss_fn = build_loss({"vgg": 0}, model, warn=False)
    batch = fake_batch()
    opt = torch.optim.SGD(model.parameters(), lr=0.05)
    for _ in range(3 if any(isinstance(m, ASPI) for m in model.modules()) else 2):
        opt.zero_grad()
        out = model(batch["turb"])
        loss, terms = loss_fn(out, batch)
        loss.backward()
        opt.step()
    assert KEYS <= set(out) and model.config["name"] == CASES[case_id][0]
    for key in ("deblurred", "restored"):
        assert out[key].shape == batch["turb"].shape and torch.isfinite(out[key]).all()
    assert out["guide"].shape[-2:] == (67, 93)
    two_stage = case_id.startswith("d2turb")
    assert (out["bwd_flow_px"] is not None) == two_stage
    assert set(terms) == {"photo"} | ({"deblur", "flow"} if two_stage else set()) | OWN_TERMS[case_id]
    assert torch.isfinite(loss)
    for name, p in model.named_parameters():
        assert p.grad is not None, name
        assert torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, f"{name} received no gradient"


@pytest.mark.parametrize("case_id", ["turbnet", "atnet", "focalnet"])
def test_training_only_outputs_vanish_in_eval(case_id):
    model = build(case_id).eval()
    with torch.no_grad():
        out = model(torch.rand(1, 3, 35, 41))
    assert KEYS <= set(out) and not {"redegraded", "prior", "restored_half"} & set(out)
    backbone = getattr(model, "backbone", model)
    assert build_loss({"vgg": 0}, model, warn=False).extra(out, fake_batch(35, 41)) == {}
    assert getattr(backbone, "_side", None) is None


# ------------------------------------------------------------------ parameter counts (meta device, no forward)
@pytest.mark.parametrize(
    "method, name, cfg, paper", [(m, n, c, p) for m, n, c, p, _ in PAPER_EFFICIENCY if m not in ("AT-Net", "TMT")]
)
def test_parameter_counts_match_the_paper(method, name, cfg, paper):
    """Within 2 % of the D²Turb paper's efficiency table (AT-Net and TMT: see the two tests below)."""
    assert parameter_count(name, **cfg) == pytest.approx(paper * 1e6, rel=0.02), method


def test_tmt_single_frame_count_plus_dead_temporal_taps_is_the_published_count():
    """The 2-D single-frame TMT, plus the outer taps of its 3-frame kernels that a single frame never reaches,
    gives the paper's 22.75 M; the 2-D network itself is smaller."""
    with torch.device("meta"):
        model = create_model("tmt")
    assert published_parameter_count(model) == pytest.approx(22.75e6, rel=0.005)
    assert parameter_count("tmt") == pytest.approx(14.97e6, rel=0.005)


def test_atnet_count_relates_to_the_paper_as_documented():
    """Paper 3.05 M ≈ one stream as executed by the released code, whose forward never reaches one of the five
    half-resolution Res2Net blocks (+ its transition and side conv): within 2 %. Both streams are 2 × 3.49 M."""
    with torch.device("meta"):
        model = create_model("atnet")
    stream = sum(p.numel() for p in model.main.parameters())
    never_run = (model.main.mid[3], model.main.mid_trans[3], model.main.side[2])
    skipped = sum(p.numel() for m in never_run for p in m.parameters())
    assert stream - skipped == pytest.approx(3.05e6, rel=0.02)
    assert parameter_count("atnet") == pytest.approx(2 * 3.49e6, rel=0.01)


@pytest.mark.parametrize("preset, backbone", [("d2turb_focalnet", "focalnet"), ("d2turb_adair", "adair")])
def test_d2turb_presets_are_d2turb_on_that_backbone(preset, backbone):
    """The presets are ``d2turb`` with another backbone: the authors' rectifier and ASPI by default, fed the
    backbone's own F_guide; every other keyword of ``d2turb`` (here the ``unet`` rectifier) passes through."""
    for cfg in ({}, {"rectifier": "unet", "injection": "aspi_cosine", "injection_cfg": {"heads": 2}}):
        with torch.device("meta"):
            model = create_model(preset, **cfg)
            ref = create_model("d2turb", backbone=backbone, **cfg)
        assert {k: v.shape for k, v in model.state_dict().items()} == {k: v.shape for k, v in ref.state_dict().items()}
    with torch.device("meta"):
        model = create_model(preset)
    assert model.backbone.config["name"] == backbone and isinstance(model.rectifier, TiltRectifier)
    assert isinstance(model.rectifier.inject, ASPI)
    assert (
        model.rectifier.inject.key.in_channels
        == model.backbone.guide_channels
        == {"focalnet": 32, "adair": 96}[backbone]
    )
    rect = sum(p.numel() for p in model.rectifier.parameters())
    assert parameter_count(preset) == parameter_count(backbone) + rect
    # the same rectifier as the paper model's (31,823,767 − 26,126,644), less the K/V rows of a narrower F_guide
    assert rect == 31_823_767 - 26_126_644 - 2 * 32 * (96 - model.backbone.guide_channels)


# ------------------------------------------------------------------ building blocks vs independent oracles
def test_fft_l1_of_a_constant_offset():
    """FFT of a constant δ over N pixels is δ·N at DC and 0 elsewhere: the mean |·| over the 2N real/imag
    entries is δ/2."""
    a = torch.rand(2, 3, 8, 12)
    assert fft_l1(a + 0.3, a).item() == pytest.approx(0.15, rel=1e-5)


def test_adair_mask_is_the_published_box_with_a_straight_through_gradient():
    """Forward: AdaIR's mask rows ⌊n/2⌋−k … ⌊n/2⌋+k−1 (k = ⌊half⌋), written here by slicing; backward: nonzero."""
    half = torch.tensor([0.4, 1.7, 2.0, 3.9], requires_grad=True)
    for n in (8, 9):
        mask = _box(n, half)
        expect = torch.zeros(4, n)
        for i, k in enumerate(half.detach().floor().int().tolist()):
            expect[i, n // 2 - k : n // 2 + k] = 1
        assert torch.equal(mask.detach(), expect)
    mask.sum().backward()
    assert (half.grad > 0).all()


def _copy_restormer(src, norm_bias=True):
    cfg = {**TINY_RESTORMER, "norm_bias": norm_bias}
    ref = Restormer(**cfg)
    missing, unexpected = ref.load_state_dict(src.state_dict(), strict=False)
    assert not missing and unexpected  # every Restormer weight comes from the method; the method has more
    return ref.eval()


def test_adair_at_init_is_restormer_and_turbnet_j_is_restormer():
    """AdaIR's frequency blocks enter through zero-initialised gains, and TurbNet's J branch is a Restormer:
    both must compute exactly what a Restormer (WithBias LayerNorm) holding their weights computes."""
    x = torch.rand(1, 3, 37, 45)
    adair = build("adair").eval()
    turbnet = build("turbnet").eval()
    with torch.no_grad():
        torch.testing.assert_close(adair(x)["restored"], _copy_restormer(adair.backbone)(x)[0])
        torch.testing.assert_close(turbnet(x)["restored"], _copy_restormer(turbnet)(x)[0])


@pytest.mark.parametrize("case_id", ["focalnet", "d2turb_focalnet"])
def test_focalnet_terms_vanish_for_a_perfect_prediction_at_every_scale(case_id):
    """With its output heads zeroed, FocalNet predicts its (padded) input at full, ½ and ¼ scale (nearest
    downsampling). For an image constant on 4×4 blocks, padded by replication (sides 12×20 < the pad to 32 inside
    D²Turb) and given as its own target, those are exactly the bilinearly downscaled target: every term must be 0,
    which holds only if the target is padded to the canvas the backbone saw."""
    model = build(case_id).train()
    backbone = getattr(model, "backbone", model)
    with torch.no_grad():
        for head in (backbone.output, backbone.out2[0], backbone.out4[0]):
            head.weight.zero_()
            head.bias.zero_()
    image = torch.rand(1, 3, 3, 5, generator=torch.Generator().manual_seed(0)).repeat_interleave(4, -2)
    image = image.repeat_interleave(4, -1)  # (1, 3, 12, 20)
    batch = {"turb": image, "gt": image, "tilt": image}
    out = model(image)
    terms = backbone.extra_loss(out, batch)
    assert backbone.multiple == 4 and set(terms) == {"multiscale", "fft"}
    assert terms["multiscale"].item() < 1e-6 and terms["fft"].item() < 1e-4


def test_turbnet_redegradation_term():
    model = build("turbnet").train()
    batch = fake_batch(24, 24)
    out = model(batch["turb"])
    expect = (out["redegraded"] - batch["turb"]).abs().mean() / 9  # (1 − α)/α with α = 0.9
    torch.testing.assert_close(model.extra_loss(out, batch)["redegrade"], expect)


def test_tmt_shuffle_mixes_groups_then_interleaves():
    """Oracle written with loops: output channel c'·G + g = Σ_j W[g, j] · input channel j·C' + c' + b[g]."""
    torch.manual_seed(0)
    att = ShuffleAttention(8, 2, bias=False, groups=4)
    qkv = torch.randn(1, 24, 3, 5)
    b, _, h, w = qkv.shape
    got = att.shuffle(qkv.reshape(b, 4, -1, h, w).permute(0, 2, 3, 4, 1)).permute(0, 1, 4, 2, 3).reshape(b, -1, h, w)
    wgt, bias = att.shuffle.weight, att.shuffle.bias
    expect = torch.empty_like(qkv)
    for c in range(6):
        for g in range(4):
            expect[:, c * 4 + g] = sum(wgt[g, j] * qkv[:, j * 6 + c] for j in range(4)) + bias[g]
    torch.testing.assert_close(got, expect)


def test_atnet_uncertainty_comes_from_mc_dropout_in_eval():
    """The prior stream keeps dropout on at inference: σ > 0 somewhere; a fixed seed reproduces the output."""
    model = build("atnet").eval()
    x = torch.rand(1, 3, 20, 22)
    outs = []
    for seed in (0, 0, 1):
        torch.manual_seed(seed)
        with torch.no_grad():
            outs.append(model(x))
    assert outs[0]["uncertainty"].shape == x.shape and outs[0]["uncertainty"].max() > 0
    assert torch.equal(outs[0]["restored"], outs[1]["restored"])
    assert not torch.equal(outs[0]["uncertainty"], outs[2]["uncertainty"])


@pytest.mark.parametrize("preset", ["d2turb_focalnet", "d2turb_adair"])
def test_preset_files_written_before_format_2_load_with_their_old_defaults(tmp_path, preset):
    """Weights saved before the authors' rectifier became the default (no ``d2turb_format`` key): the presets then
    meant the U-Net rectifier and the cosine ASPI, and such a file must load as exactly that model."""
    from safetensors.torch import save_file

    from d2turb.models import load_pretrained
    from d2turb.models.weights import tensors_sha256

    backbone_cfg = TINY_FOCALNET if preset == "d2turb_focalnet" else TINY_ADAIR
    rect = {"width": 8, "mults": [1, 1, 2, 2], "depth": 3}
    old = {"backbone_cfg": backbone_cfg, "rectifier_cfg": rect, "injection_cfg": {"heads": 2}}
    then = dict(old, rectifier="unet", injection="aspi_cosine")
    torch.manual_seed(0)
    model = create_model(preset, **then).eval()
    tensors = {k: v.contiguous() for k, v in model.state_dict().items()}
    meta = {"d2turb_config": json.dumps({"name": preset, **old}), "d2turb_sha256": tensors_sha256(tensors)}
    save_file(tensors, str(tmp_path / "old.safetensors"), metadata=meta)
    loaded = load_pretrained(tmp_path / "old.safetensors")
    assert loaded.config == json.loads(json.dumps({"name": preset, **then}))
    x = torch.rand(1, 3, 32, 32)
    with torch.no_grad():
        assert torch.equal(loaded(x)["restored"], model(x)["restored"])


# ------------------------------------------------------------------ configs, training and restoring via the CLI
METHOD_CONFIGS = ["atnet", "turbnet", "tmt", "focalnet", "adair", "d2turb_focalnet_aspi", "d2turb_adair_aspi"]


@pytest.mark.parametrize("stem", METHOD_CONFIGS)
def test_method_configs_follow_the_d2turb_recipe(stem):
    cfg = load_config(REPO / "configs" / f"{stem}.yaml")
    ref = load_config(REPO / "configs" / "d2turb_restormer_aspi.yaml")
    same = (("train", ("epochs", "batch", "lr", "lr_min", "betas", "seed")), ("data", ("patch", "pairs")))
    for section, keys in same:
        ours, paper = getattr(cfg, section), getattr(ref, section)
        assert {k: getattr(ours, k) for k in keys} == {k: getattr(paper, k) for k in keys}, section
    assert (cfg.loss.photo, cfg.loss.vgg) == (1.0, 0.02)
    assert cfg.model["name"] in {name for _, name, _, _, _ in PAPER_EFFICIENCY}
    if stem.startswith("d2turb_"):  # the D²Turb recipe in full, on the paper model's rectifier and injection
        assert vars(cfg.loss) == vars(ref.loss)
        assert {k: v for k, v in cfg.model.items() if k != "name"} == {"rectifier": "authors", "injection": "aspi"}


@pytest.mark.parametrize("case_id", CASES)
def test_train_then_restore_via_cli(case_id, tmp_path, capsys):
    from test_train import make_pairs

    pairs = make_pairs(tmp_path / "pairs", n=4, size=32)
    name, model_cfg = CASES[case_id]
    cfg = {
        "model": {"name": name, **model_cfg},
        "data": {"pairs": str(pairs), "patch": 32, "num_workers": 0, "hflip": False},
        "train": {"iterations": 2, "batch": 2, "lr": 1e-3, "device": "cpu"},
        "loss": {"vgg": 0},
        "log": {"every": 1, "progress": False},
    }
    (tmp_path / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    run = tmp_path / "run"
    assert main(["train", "--config", str(tmp_path / "cfg.yaml"), "--out", str(run)]) == 0
    logged = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert logged[-1]["iter"] == 2 and OWN_TERMS[case_id] <= set(logged[-1])
    img = pairs / "turb" / "0000000.png"
    assert main(["restore", str(img), "--weights", str(run / "model.safetensors"), "--out", str(tmp_path / "o")]) == 0
    from d2turb.io import read_image

    restored = read_image(tmp_path / "o" / "0000000_restored.png")
    assert restored.shape == (3, 32, 32) and torch.isfinite(restored).all()
    capsys.readouterr()
