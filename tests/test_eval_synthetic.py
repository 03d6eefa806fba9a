"""Synthetic evaluation: per-bin metrics against analytic / scikit-image oracles, reports, LPIPS policy."""

import json
import math

import numpy as np
import pytest
import torch
from hostile_input import error_lines, run_cli, tiny_pairs
from PIL import Image
from skimage.metrics import structural_similarity
from torch import nn

from d2turb.errors import D2TurbError
from d2turb.eval.synthetic import evaluate_synthetic
from d2turb.io import write_image

SIZE = 40
OFFSETS = {"weak": 2, "medium": 5, "strong": 10}  # turb = gt + k/255 exactly (gt in [0.2, 0.8]): MSE = (k/255)^2
DR0 = {"weak": 1.5, "medium": 3.0, "strong": 4.5}


def _gt(seed):
    rng = np.random.default_rng(seed)
    smooth = rng.random((SIZE // 4, SIZE // 4, 3)).repeat(4, 0).repeat(4, 1)  # some structure for SSIM
    return np.round((0.2 + 0.6 * smooth) * 255).astype(np.uint8)


def write_tiny_dataset(root, per_bin=(2, 1, 2)):
    """A few-line writer of the make-dataset layout (d2turb/data/layout.py): dataset.json, meta.jsonl,
    {turb,tilt,gt,depth}/<id>.png and bwd_flow_px/<id>.npy."""
    for kind in ("turb", "tilt", "gt", "bwd_flow_px", "depth"):
        (root / kind).mkdir(parents=True)
    meta, index = [], 0
    for bin_name, n in zip(OFFSETS, per_bin):
        for _ in range(n):
            sid = f"{index:07d}"
            gt = _gt(index)
            Image.fromarray(gt).save(root / "gt" / f"{sid}.png")
            Image.fromarray(gt + OFFSETS[bin_name]).save(root / "turb" / f"{sid}.png")
            Image.fromarray(gt).save(root / "tilt" / f"{sid}.png")
            Image.fromarray(np.full((SIZE, SIZE), 30000, np.uint16)).save(root / "depth" / f"{sid}.png")
            np.save(root / "bwd_flow_px" / f"{sid}.npy", np.zeros((2, SIZE, SIZE), np.float16))
            meta.append({"id": sid, "index": index, "dr0": DR0[bin_name], "bin": bin_name, "split": "test"})
            index += 1
    (root / "meta.jsonl").write_text("".join(json.dumps(m) + "\n" for m in meta))
    (root / "dataset.json").write_text(
        json.dumps({"version": 1, "pairs": index, "patch": SIZE, "split": "test", "bins": list(OFFSETS)})
    )
    return root


class MinusTwo(nn.Module):
    """Undoes the weak bin's offset exactly (so its weak PSNR hits the 100 dB cap)."""

    def forward(self, x):
        y = x - 2 / 255
        return {"deblurred": y, "restored": y, "flow": torch.zeros_like(x[:, :2])}


@pytest.fixture
def no_lpips(monkeypatch, tmp_path):
    for var in ("D2TURB_LPIPS_WEIGHTS", "D2TURB_LPIPS_BACKBONE"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("D2TURB_CACHE_DIR", str(tmp_path / "empty-cache"))


def test_per_bin_metrics_match_oracles(tmp_path, no_lpips):
    data = write_tiny_dataset(tmp_path / "data")
    res = evaluate_synthetic(["input", MinusTwo()], data, tmp_path / "out")
    table = res["table"]
    # input baseline: PSNR = -10 log10((k/255)^2) exactly, per bin; Avg = mean over all 5 samples
    expected = {b: -20 * math.log10(k / 255) for b, k in OFFSETS.items()}
    for b in OFFSETS:
        assert table["input"]["psnr"][b] == pytest.approx(expected[b], abs=1e-3)
    avg = (2 * expected["weak"] + expected["medium"] + 2 * expected["strong"]) / 5
    assert table["input"]["psnr"]["avg"] == pytest.approx(avg, abs=1e-3)
    assert table["MinusTwo"]["psnr"]["weak"] == pytest.approx(100.0)  # exact restoration, capped
    # SSIM against scikit-image (Gaussian 1.5, population covariance, as Wang et al. 2004)
    for s in res["per_sample"]:
        gt = np.asarray(Image.open(data / "gt" / f"{s['id']}.png")) / 255.0
        turb = np.asarray(Image.open(data / "turb" / f"{s['id']}.png")) / 255.0
        ref = structural_similarity(
            turb, gt, channel_axis=2, data_range=1.0, gaussian_weights=True, sigma=1.5, use_sample_covariance=False
        )
        assert s["values"]["input"]["ssim"] == pytest.approx(ref, abs=1e-4)
    assert res["bin_counts"] == {"weak": 2, "medium": 1, "strong": 2}
    # missing LPIPS weights with default metrics: column omitted, visible note
    assert res["metrics"] == ["psnr", "ssim"] and "LPIPS column omitted" in res["notes"][0]
    md = (tmp_path / "out" / "results.md").read_text()
    assert "LPIPS column omitted" in md and "LPIPS↓" not in md
    assert json.loads((tmp_path / "out" / "results.json").read_text())["table"] == json.loads(json.dumps(table))


def test_report_table_and_grids(tmp_path, no_lpips):
    from d2turb.eval.report import grid_cell_origin

    data = write_tiny_dataset(tmp_path / "data")
    evaluate_synthetic(["input", MinusTwo()], data, tmp_path / "out", max_samples=4, grid_per_bin=1)
    md = (tmp_path / "out" / "results.md").read_text().splitlines()
    header = next(line for line in md if line.startswith("| Method"))
    assert header.split(" | ")[1:5] == ["PSNR↑ weak", "medium", "strong", "**Avg**"]
    rows = {
        line.split(" | ")[0][2:]: line for line in md if line.startswith("| input") or line.startswith("| MinusTwo")
    }
    assert "**100.000**" in rows["MinusTwo"] and "<u>42.110</u>" in rows["input"]  # best bold, second underlined
    tex = (tmp_path / "out" / "results.tex").read_text()
    assert r"\multicolumn{4}{c}{PSNR$\uparrow$}" in tex and r"\textbf{100.000}" in tex
    # grids: one per bin present in the first 4 samples; columns input | GT | MinusTwo (the "input" model
    # would duplicate column 1 and is left out); the GT cell holds the GT image
    grids = sorted(p.name for p in (tmp_path / "out" / "grids").iterdir())
    assert grids == ["medium.png", "strong.png", "weak.png"]
    grid = np.asarray(Image.open(tmp_path / "out" / "grids" / "weak.png"))
    label = "weak: 0000000  D/r0=1.50"
    y, x = grid_cell_origin(0, 1, [label], cell=SIZE)  # cells shrink to the 40 px images
    np.testing.assert_array_equal(grid[y : y + SIZE, x : x + SIZE], _gt(0))
    y, x = grid_cell_origin(0, 2, [label], cell=SIZE)
    np.testing.assert_array_equal(grid[y : y + SIZE, x : x + SIZE], _gt(0))  # MinusTwo restores weak exactly
    assert grid.shape[1] == x + SIZE + 4  # exactly three columns


def _random_lpips_files(tmp_path):
    from safetensors.torch import save_file

    from d2turb.eval.vgg import CHANNELS, FeatureExtractor

    torch.manual_seed(0)
    save_file(FeatureExtractor("alex").state_dict(), str(tmp_path / "alex_backbone.safetensors"))
    save_file(
        {f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1) for i, c in enumerate(CHANNELS["alex"])},
        str(tmp_path / "alex_lin.safetensors"),
    )
    return tmp_path / "alex_lin.safetensors", tmp_path / "alex_backbone.safetensors"


def test_lpips_column_with_local_weights(tmp_path, no_lpips):
    from d2turb.eval.lpips import LPIPS

    data = write_tiny_dataset(tmp_path / "data", per_bin=(1, 1, 1))
    lin, backbone = _random_lpips_files(tmp_path)
    res = evaluate_synthetic(["input"], data, tmp_path / "out", lpips_weights=lin, lpips_backbone=backbone)
    assert res["metrics"] == ["psnr", "ssim", "lpips"] and not res["notes"]
    model = LPIPS("alex", weights=lin, backbone=backbone)
    for s in res["per_sample"]:
        gt = torch.from_numpy(np.asarray(Image.open(data / "gt" / f"{s['id']}.png")) / 255.0).permute(2, 0, 1).float()
        turb = (
            torch.from_numpy(np.asarray(Image.open(data / "turb" / f"{s['id']}.png")) / 255.0).permute(2, 0, 1).float()
        )
        assert s["values"]["input"]["lpips"] == pytest.approx(float(model(turb[None], gt[None])[0]), rel=1e-5)
    assert "LPIPS↓ weak" in (tmp_path / "out" / "results.md").read_text()


def test_explicit_lpips_without_weights_is_an_error(tmp_path, no_lpips, monkeypatch):
    data = write_tiny_dataset(tmp_path / "data", per_bin=(1, 0, 0))
    with pytest.raises(D2TurbError, match="LPIPS needs"):
        evaluate_synthetic(["input"], data, tmp_path / "out", metrics=("psnr", "lpips"))
    res = evaluate_synthetic(["input"], data, tmp_path / "ok", metrics=("psnr", "ssim", "lpips"))  # the default set
    assert res["metrics"] == ["psnr", "ssim"] and res["notes"]
    monkeypatch.setenv("D2TURB_LPIPS_WEIGHTS", str(tmp_path / "missing.pth"))  # pointed to → must exist
    with pytest.raises(D2TurbError, match="LPIPS"):
        evaluate_synthetic(["input"], data, tmp_path / "out")
    with pytest.raises(D2TurbError, match="unknown metric 'fid'"):
        evaluate_synthetic(["input"], data, tmp_path / "out", metrics=("fid",))
    with pytest.raises(D2TurbError, match="at least one model"):
        evaluate_synthetic([], data, tmp_path / "out")
    with pytest.raises(D2TurbError, match="not a d2turb dataset"):
        evaluate_synthetic(["input"], tmp_path, tmp_path / "out")
    assert not (tmp_path / "out").exists()  # nothing half-written on failure


def test_flow_to_rgb_colour_wheel():
    from d2turb.eval.report import flow_to_rgb

    flow = torch.zeros(2, 1, 6)
    flow[:, 0, 1] = torch.tensor([2.0, 0.0])  # +x at the maximum magnitude: pure red
    flow[:, 0, 2] = torch.tensor([-2.0, 0.0])  # −x: cyan
    flow[:, 0, 3] = torch.tensor([0.0, 2.0])  # +y (down): hue 1/4 = (0.5, 1, 0)
    flow[:, 0, 4] = torch.tensor([1.0, 0.0])  # half the maximum to the right: half-saturated red
    flow[:, 0, 5] = torch.tensor([0.0, -2.0])  # −y: hue 3/4 = (0.5, 0, 1)
    rgb = flow_to_rgb(flow)[:, 0].T
    expected = torch.tensor(
        [[1, 1, 1], [1, 0, 0], [0, 1, 1], [0.5, 1, 0], [1, 0.5, 0.5], [0.5, 0, 1]], dtype=torch.float32
    )
    torch.testing.assert_close(rgb, expected, atol=1e-6, rtol=0)


def test_record_without_dr0_is_skipped_with_one_error_line(tmp_path, no_lpips, capsys):
    """`evaluate --data` over a dataset whose meta line 3 lacks dr0: that record is one `error:` line naming the
    file and line, every other record is evaluated (the input baseline's exact PSNR per bin), exit 1."""
    from d2turb.cli import main

    data = write_tiny_dataset(tmp_path / "data")
    lines = (data / "meta.jsonl").read_text().splitlines()
    broken = json.loads(lines[2])  # sample 0000002, the medium bin's only one
    del broken["dr0"]
    lines[2] = json.dumps(broken)
    (data / "meta.jsonl").write_text("\n".join(lines) + "\n")
    out = tmp_path / "o"
    rc = main(["evaluate", "--data", str(data), "--weights", "input", "--metrics", "psnr", "--out", str(out)])
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("error: ")]
    assert rc == 1 and "Traceback" not in err
    assert len(errors) == 1 and "meta.jsonl line 3" in errors[0] and "dr0" in errors[0]
    res = json.loads((out / "results.json").read_text())
    assert [s["id"] for s in res["per_sample"]] == ["0000000", "0000001", "0000003", "0000004"]
    assert res["bin_counts"] == {"weak": 2, "medium": 0, "strong": 2}
    assert res["table"]["input"]["psnr"]["strong"] == pytest.approx(-20 * math.log10(10 / 255), abs=1e-3)
    assert len(res["skipped"]) == 1 and "line 3" in res["skipped"][0]["error"]


def test_evaluate_data_skips_a_broken_sample(tmp_path, capsys):
    root = tmp_path / "ds"
    meta = []
    for i in range(3):
        sid = f"{i:07d}"
        image = torch.rand(3, 16, 16, generator=torch.Generator().manual_seed(i))
        for kind in ("turb", "tilt", "gt"):
            write_image(root / kind / f"{sid}.png", image)
        write_image(root / "depth" / f"{sid}.png", image[:1])
        (root / "bwd_flow_px").mkdir(exist_ok=True)
        np.save(root / "bwd_flow_px" / f"{sid}.npy", np.zeros((2, 16, 16), np.float16))
        meta.append({"id": sid, "index": i, "dr0": 3.0, "bin": "medium", "split": "test"})
    (root / "meta.jsonl").write_text("".join(json.dumps(m) + "\n" for m in meta))
    (root / "dataset.json").write_text(json.dumps({"version": 1, "pairs": 3, "patch": 16, "split": "test"}))
    (root / "turb" / "0000001.png").write_bytes(b"\x89PNG\r\n\x1a\ncut")
    out = tmp_path / "out"
    rc, _, err = run_cli(
        capsys, ["evaluate", "--data", str(root), "--weights", "input", "--metrics", "psnr", "--out", str(out)]
    )
    assert rc == 1
    lines = error_lines(err)
    assert len(lines) == 1 and "0000001" in lines[0]
    results = json.loads((out / "results.json").read_text())
    assert results["samples_evaluated"] == 2 and [s["id"] for s in results["skipped"]] == ["0000001"]


def test_evaluate_epe_skips_a_flow_of_the_wrong_size(tmp_path, capsys):
    root = tiny_pairs(tmp_path / "ds", n=3, size=16, split="test")
    np.save(root / "bwd_flow_px" / "0000001.npy", np.zeros((2, 8, 8), np.float16))
    out = tmp_path / "o"
    rc, _, err = run_cli(
        capsys, ["evaluate", "--data", str(root), "--weights", "input", "--metrics", "epe", "--out", str(out)]
    )
    assert rc == 1
    lines = error_lines(err)
    assert len(lines) == 1 and "0000001" in lines[0] and "flow" in lines[0] and "Traceback" not in err
    results = json.loads((out / "results.json").read_text())
    assert results["samples_evaluated"] == 2 and [s["id"] for s in results["skipped"]] == ["0000001"]
    assert results["table"]["input"]["epe"]["avg"] == 0.0  # zero flow against zero flow
