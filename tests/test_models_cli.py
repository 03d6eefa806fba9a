"""`d2turb models` and `d2turb bench model` (tiny configs; FLOPs counted on the meta device)."""

import json
from pathlib import Path

import pytest
import torch

from d2turb.cli import main
from d2turb.models import count_parameters, create_model, flop_counts, load_pretrained

TINY_NAFNET = {"width": 8, "enc_blocks": [1, 1], "middle_blocks": 1, "dec_blocks": [1, 1]}


def test_models_lists_models_and_backbones_with_counts(capsys):
    assert main(["models", "--json"]) == 0
    listing = json.loads(capsys.readouterr().out)
    models = {m["name"]: m["params"] for m in listing["models"]}
    assert {"d2turb", "d2turb_lite", "restormer", "nafnet"} <= set(models)
    assert models["nafnet"] == count_parameters(create_model("nafnet"))
    guides = {b["name"]: b["guide_channels"] for b in listing["backbones"]}
    assert guides.items() >= {"restormer": 96, "nafnet": 16, "adair": 96, "focalnet": 32}.items()
    # the paper's 31.82 M / 26.13 M, exactly the authors' released model definition
    assert models["d2turb"] == 31_823_767 and models["restormer"] == 26_126_644
    assert {b["name"]: b["params"] for b in listing["backbones"]}["restormer"] == 26_126_644
    assert main(["models"]) == 0
    out = capsys.readouterr().out
    assert "d2turb           31.82 M" in out and "restormer        26.13 M" in out
    shipped = "nafnet-gpu-spectral3*, nafnet-cpu-small, nafnet-cpu-spectral, nafnet-gpu-spectral2"
    assert f"nafnet            1.14 M  shipped: {shipped}" in out


def test_models_weights_column_says_how_to_get_weights(capsys):
    """Each model's weights: the shipped files that hold it (read from the files' own metadata), else a training
    config of configs/ that names the model; the paper model also through the authors' checkpoint."""
    import yaml
    from safetensors import safe_open

    from d2turb.models.hub import shipped_weights_dir

    assert main(["models", "--json"]) == 0
    models = {m["name"]: m["weights"] for m in json.loads(capsys.readouterr().out)["models"]}
    holds: dict[str, list[str]] = {}
    for path in sorted(shipped_weights_dir().glob("*.safetensors")):
        with safe_open(str(path), "pt") as f:
            holds.setdefault(json.loads(f.metadata()["d2turb_config"])["name"], []).append(path.stem)
    configs = Path(__file__).resolve().parents[1] / "configs"
    for name, weights in models.items():
        assert sorted(weights["shipped"]) == sorted(holds.get(name, [])), name
        if not weights["shipped"]:
            config = configs / weights["train"].rsplit("configs/", 1)[1]
            assert yaml.safe_load(config.read_text())["model"]["name"] == name, (name, config)
    assert "convert" in models["d2turb"] and models["nafnet"]["shipped"]


def test_bench_model_json(tmp_path, capsys):
    out = tmp_path / "b.json"
    cfg = json.dumps({"backbone_cfg": TINY_NAFNET, "rectifier_cfg": {"widths": [8, 8, 16, 16]}})
    assert (
        main(
            [
                "bench",
                "model",
                "d2turb",
                "--backbone",
                "nafnet",
                "--injection",
                "concat",
                "--config",
                cfg,
                "--size",
                "32",
                "--repeats",
                "1",
                "--warmup",
                "0",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    r = json.loads(out.read_text())
    model = create_model("d2turb", **json.loads(cfg), backbone="nafnet", injection="concat")
    assert r["params"] == count_parameters(model)
    assert r["flops"] == flop_counts(model, 32)["total"] and r["gmacs"] == pytest.approx(r["flops"] / 2e9)
    assert r["latency_s"] > 0 and r["config"]["injection"] == "concat"
    assert "| d2turb (" in capsys.readouterr().out


def test_bench_model_d2turb_reports_the_paper_model(tmp_path, capsys):
    """Acceptance: `d2turb bench model d2turb` is the paper's model: 31,823,767 parameters (31.82 M), Restormer
    26,126,644 (26.13 M) and 140.99 G convolution MACs at 256² (the Restormer paper's figure)."""
    out = tmp_path / "d2turb.json"
    assert main(["bench", "model", "d2turb", "--no-latency", "--out", str(out)]) == 0
    assert json.loads(out.read_text())["params"] == 31_823_767
    assert "| d2turb | 31.82 |" in capsys.readouterr().out
    assert main(["bench", "model", "restormer", "--no-latency", "--out", str(out)]) == 0
    r = json.loads(out.read_text())
    assert r["params"] == 26_126_644 and r["conv_gmacs"] == pytest.approx(140.99, abs=0.005)
    assert "| restormer | 26.13 | 26.13 | -0.0% | 154.88 | 140.99 |" in capsys.readouterr().out


def test_flops_of_a_single_conv_match_the_formula():
    """Independent oracle for the counter: a 3×3 conv C_in→C_out on H×W costs 2·C_in·C_out·9·H·W FLOPs."""
    conv = torch.nn.Conv2d(3, 5, 3, padding=1, bias=False)
    assert flop_counts(conv, (12, 20))["aten.convolution"] == 2 * 3 * 5 * 9 * 12 * 20


@pytest.mark.slow
def test_bench_all_writes_markdown_table(tmp_path):
    """The paper's efficiency table, its values beside ours, then the project's other models."""
    from d2turb.models.complexity import PAPER_EFFICIENCY

    out = tmp_path / "table.md"
    assert main(["bench", "model", "--all", "--no-latency", "--out", str(out)]) == 0
    text = out.read_text()
    for method, _, _, paper, _ in PAPER_EFFICIENCY:
        assert f"| {method}" in text and f"| {paper:.2f} |" in text, method
    # conv GMACs = Restormer's published 140.99
    assert "| Restormer | restormer | 26.13 | 26.13 | -0.0% | 154.88 | 140.99 | – |" in text
    assert "| FocalNet | focalnet | 6.77 | 6.77 |" in text
    d2turb_row = "| D²Turb+Restormer | d2turb (backbone=restormer, injection=aspi) | 31.82 | 31.82 | +0.0% |"
    assert d2turb_row in text and "| 150.51 |" in text
    assert "| D²Turb+FocalNet | d2turb_focalnet | 12.46 | 12.46 |" in text
    assert "[1] AT-Net:" in text and "[2] TMT:" in text  # differences over 2 % come with their explanation
    assert text.count("\n| ") >= 14


@pytest.mark.parametrize(
    "argv, message",
    [
        (["bench", "model"], "exactly one of"),
        (["bench", "model", "nope", "--no-latency"], "unknown model 'nope'"),
        (["bench", "model", "nafnet", "--config", "{bad", "--no-latency"], "not valid JSON"),
        (["bench", "model", "nafnet", "--out", "x.txt"], "must end in .md or .json"),
    ],
)
def test_bench_errors_are_one_line(capsys, argv, message):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and err.count("\n") == 1


FIXTURE = Path(__file__).resolve().parents[1] / ".." / "shared" / "fixtures" / "official_d2turb"


def test_convert_authors_checkpoint(tmp_path, capsys):
    """A random state dict with the authors' full layout (../shared fixture: every key and shape of their model),
    nested under params_ema with DDP's module. prefixes: refused while one key is missing (error names it, nothing
    written), then converted and loaded as the paper model (31,823,767 parameters) with its values."""
    if not FIXTURE.is_dir():
        pytest.skip(f"fixture folder {FIXTURE} is absent")
    layout = json.loads((FIXTURE / "official_state_dict_layout.json").read_text())["keys"]
    gen = torch.Generator().manual_seed(0)
    state = {k: torch.randn(shape, generator=gen).half() for k, shape in layout.items()}  # fp16, as released
    src, dst = tmp_path / "net_g_latest.pth", tmp_path / "d2turb_paper.safetensors"
    dropped = state.pop("rectifier.decode_2.body.0.bias")
    torch.save({"params_ema": {f"module.{k}": v for k, v in state.items()}}, src)
    assert main(["convert", str(src), str(dst)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and "missing: rectifier.decode_2.body.0.bias\n" in err
    assert not dst.exists() and not list(tmp_path.glob(".*tmp*"))
    state["rectifier.decode_2.body.0.bias"] = dropped
    torch.save({"params_ema": {f"module.{k}": v for k, v in state.items()}}, src)
    assert main(["convert", str(src), str(dst)]) == 0
    assert "31,823,767 parameters" in capsys.readouterr().out
    model = load_pretrained(dst)
    assert model.config == {"name": "d2turb"} and count_parameters(model) == 31_823_767
    weights = model.state_dict()
    assert torch.equal(weights["rectifier.decode_2.body.0.bias"], dropped.float())
    assert torch.equal(
        weights["backbone.encoder_level2.5.attn.project_out.weight"],
        state["restormer.encoders.1.5.attention.project_out.weight"].float(),
    )


@pytest.mark.parametrize(
    "make, dst, message",
    [
        (lambda p: torch.save({"w": torch.ones(2)}, p), "out.pt", "must end in .safetensors"),
        (None, "out.safetensors", "weights file not found"),
        (lambda p: p.write_bytes(b"not a zip"), "out.safetensors", "cannot read checkpoint"),
        (
            lambda p: torch.save({"optimizer": {"lr": 1.0}}, p),
            "out.safetensors",
            "no state dict found under params_ema",
        ),
        (lambda p: torch.save({"params": {"w": torch.ones(2)}}, p), "out.safetensors", "not weights of model 'd2turb'"),
    ],
)
def test_convert_errors_are_one_line(tmp_path, capsys, make, dst, message):
    src = tmp_path / "in.pth"
    if make:
        make(src)
    assert main(["convert", str(src), str(tmp_path / dst)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and err.count("\n") == 1
    assert not (tmp_path / dst).exists()
