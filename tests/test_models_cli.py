"""`d2turb models` and `d2turb bench model` (tiny configs; FLOPs counted on the meta device)."""

import json

import pytest
import torch

from d2turb.cli import main
from d2turb.models import count_parameters, create_model, flop_counts

TINY_NAFNET = {"width": 8, "enc_blocks": [1, 1], "middle_blocks": 1, "dec_blocks": [1, 1]}


def test_models_lists_models_and_backbones_with_counts(capsys):
    assert main(["models", "--json"]) == 0
    listing = json.loads(capsys.readouterr().out)
    models = {m["name"]: m["params"] for m in listing["models"]}
    assert {"d2turb", "d2turb_lite", "restormer", "nafnet"} <= set(models)
    assert models["nafnet"] == count_parameters(create_model("nafnet"))
    guides = {b["name"]: b["guide_channels"] for b in listing["backbones"]}
    assert guides.items() >= {"restormer": 96, "nafnet": 16, "adair": 96, "focalnet": 32}.items()
    assert main(["models"]) == 0
    assert "31.88 M" in capsys.readouterr().out


def test_bench_model_json(tmp_path, capsys):
    out = tmp_path / "b.json"
    cfg = json.dumps({"backbone_cfg": TINY_NAFNET, "rectifier_cfg": {"width": 8, "mults": [1, 1, 2, 2], "depth": 3}})
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


def test_flops_of_a_single_conv_match_the_formula():
    """Independent oracle for the counter: a 3×3 conv C_in→C_out on H×W costs 2·C_in·C_out·9·H·W FLOPs."""
    conv = torch.nn.Conv2d(3, 5, 3, padding=1, bias=False)
    assert flop_counts(conv, (12, 20))["aten.convolution"] == 2 * 3 * 5 * 9 * 12 * 20


def test_bench_all_writes_markdown_table(tmp_path):
    """The paper's efficiency table, its values beside ours, then the project's other models."""
    from d2turb.models.complexity import PAPER_EFFICIENCY

    out = tmp_path / "table.md"
    assert main(["bench", "model", "--all", "--no-latency", "--out", str(out)]) == 0
    text = out.read_text()
    for method, _, _, paper, _ in PAPER_EFFICIENCY:
        assert f"| {method}" in text and f"| {paper:.2f} |" in text, method
    # conv GMACs = Restormer's published 140.99
    assert "| Restormer | restormer | 26.11 | 26.13 | -0.1% | 154.88 | 140.99 | – |" in text
    assert "| FocalNet | focalnet | 6.77 | 6.77 |" in text
    assert "| D²Turb+Restormer | d2turb (backbone=restormer, injection=aspi) |" in text and "| 150.51 |" in text
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
