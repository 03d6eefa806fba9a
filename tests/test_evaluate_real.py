"""`d2turb evaluate --real`: per-image no-reference metrics, models, grids, errors; --data dispatch."""

import json
import sys
import types

import numpy as np
import pytest
import torch
from hostile_input import error_lines, png_bomb, run_cli
from PIL import Image, ImageDraw, ImageFont

from d2turb.cli import main
from d2turb.errors import D2TurbError, print_error
from d2turb.eval.niqe import niqe
from d2turb.eval.piqe import piqe
from d2turb.eval.real import GRID_LABEL_H, evaluate_real
from d2turb.io import read_image, write_image

NIQE_MATLAB = {"I03.png": 15.7536, "I04.png": 3.6549, "I06.png": 3.2355, "I08.png": 3.1840, "I19.png": 8.6352}


@pytest.fixture
def real_dir(tmp_path, astronaut):
    folder = tmp_path / "real"
    write_image(folder / "a.png", astronaut[0, :, :192, :160])
    write_image(folder / "b.png", astronaut[0, :, 40:, 30:].flip(-1))
    return folder


def _blur_factory(calls):
    def factory(weights, device):
        calls.append((weights, device))
        return lambda img: torch.nn.functional.avg_pool2d(img[None], 5, 1, 2, count_include_pad=False)[0]

    return factory


def test_acceptance_command_on_calibration_images(shared_data, tmp_path, capsys):
    dist = shared_data / "iqa_calibration" / "dist"
    out = tmp_path / "out"
    assert main(["evaluate", "--real", str(dist), "--metrics", "niqe", "--out", str(out)]) == 0
    results = json.loads((out / "results.json").read_text())
    per_image = results["niqe"]["per_image"]
    assert set(per_image) == set(NIQE_MATLAB)
    for name, expected in NIQE_MATLAB.items():
        assert per_image[name] == pytest.approx(expected, abs=0.05)
    assert results["niqe"]["mean"] == pytest.approx(np.mean(list(per_image.values())), abs=1e-12)
    assert results["models"]["input"]["niqe"] == results["niqe"]
    md = (out / "results.md").read_text()
    assert "| input |" in md and "I19.png" in md
    assert "input: niqe" in capsys.readouterr().out


def test_models_rows_values_and_grids(real_dir, tmp_path):
    calls = []
    out = tmp_path / "out"
    results = evaluate_real(
        real_dir, "niqe,piqe", out, weights=["input", "runs/blur.safetensors"], restorer_factory=_blur_factory(calls)
    )
    assert calls == [("runs/blur.safetensors", "cpu")]
    assert list(results["models"]) == ["input", "blur"]
    a = read_image(real_dir / "a.png")
    blurred = torch.nn.functional.avg_pool2d(a[None], 5, 1, 2, count_include_pad=False)[0]
    assert results["models"]["input"]["niqe"]["per_image"]["a.png"] == pytest.approx(niqe(a).item(), abs=1e-12)
    assert results["models"]["blur"]["piqe"]["per_image"]["a.png"] == pytest.approx(piqe(blurred).item(), abs=1e-12)
    for model in ("input", "blur"):
        for m in ("niqe", "piqe"):
            vals = results["models"][model][m]["per_image"]
            assert results["models"][model][m]["mean"] == pytest.approx((vals["a.png"] + vals["b.png"]) / 2)
    on_disk = json.loads((out / "results.json").read_text())
    assert on_disk["models"]["blur"]["niqe"]["per_image"] == results["models"]["blur"]["niqe"]["per_image"]
    grid = np.asarray(Image.open(out / "grids" / "a.png"))
    assert grid.shape == (GRID_LABEL_H + 192, 2 * 160 + 4, 3)
    np.testing.assert_array_equal(grid[GRID_LABEL_H:, :160], np.asarray(Image.open(real_dir / "a.png")))
    # the label strip names the columns: dark text over each image's column, white elsewhere
    strip = grid[:GRID_LABEL_H].min(axis=2)
    assert strip[:, :160].min() < 128 and strip[:, 164:].min() < 128 and strip[:, 160:164].min() == 255
    expected = Image.new("RGB", (grid.shape[1], GRID_LABEL_H), "white")
    draw, font = ImageDraw.Draw(expected), ImageFont.load_default()
    draw.text((2, 2), "input", fill="black", font=font)
    draw.text((164 + 2, 2), "blur", fill="black", font=font)
    np.testing.assert_array_equal(grid[:GRID_LABEL_H], np.asarray(expected))
    md = (out / "results.md").read_text()
    assert "| blur |" in md and "PIQE" in md


def test_recursive_scores_each_clip_folder_with_means_per_folder(tmp_path, astronaut, capsys):
    """One folder per clip, the same frame names in each: per-image NIQE equals the metric on the file, the
    folder means are the plain means of their frames, grids keep the folder, hidden files are not read."""
    real = tmp_path / "real"
    crops = {
        "clip1/f1.png": astronaut[0, :, :192, :160],
        "clip1/f2.png": astronaut[0, :, 64:, 96:],
        "clip2/f1.png": astronaut[0, :, 32:224, 48:208].flip(-1),
        "top.png": astronaut[0, :, 40:232, 80:240].flip(-2),
    }
    for name, crop in crops.items():
        write_image(real / name, crop)
    (real / "clip2" / "._f1.png").write_bytes(b"\x00\x05\x16\x07 AppleDouble")  # macOS metadata, not an image
    out = tmp_path / "out"
    results = evaluate_real(
        real, ["niqe"], out, weights=["input", "blur.safetensors"], restorer_factory=_blur_factory([]), recursive=True
    )
    assert results["images"] == list(crops) and results["skipped"] == []
    expected = {name: niqe(read_image(real / name)).item() for name in crops}
    per_image = results["models"]["input"]["niqe"]["per_image"]
    assert per_image == pytest.approx(expected, abs=1e-12)
    folders = results["folders"]
    assert list(folders) == ["clip1", "clip2", "."]
    assert folders["clip1"]["images"] == ["clip1/f1.png", "clip1/f2.png"]
    assert folders["clip1"]["models"]["input"]["niqe"] == pytest.approx(
        np.mean([expected["clip1/f1.png"], expected["clip1/f2.png"]])
    )
    assert folders["."]["models"]["input"]["niqe"] == pytest.approx(expected["top.png"])
    assert (out / "grids" / "clip1" / "f1.png").is_file() and (out / "grids" / "clip2" / "f1.png").is_file()
    assert json.loads((out / "results.json").read_text())["folders"] == folders
    assert "## Means per folder" in (out / "results.md").read_text()

    rc = main(["evaluate", "--real", str(real), "--recursive", "--metrics", "niqe", "--out", str(tmp_path / "o2")])
    assert rc == 0 and "clip2 (1 image), input: niqe" in capsys.readouterr().out
    assert main(["evaluate", "--real", str(real / "clip1"), "--recursive", "--out", str(tmp_path / "o3")]) == 0


def test_clip_folders_without_recursive_and_recursive_with_data_are_one_line_errors(tmp_path, astronaut, capsys):
    real = tmp_path / "real"
    write_image(real / "clip" / "f.png", astronaut[0, :, :192, :160])
    assert main(["evaluate", "--real", str(real), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "no images found" in err and "--recursive" in err and err.count("\n") == 1
    assert (
        main(["evaluate", "--data", str(real), "--weights", "input", "--recursive", "--out", str(tmp_path / "o")]) == 2
    )
    assert "--recursive goes with --real" in capsys.readouterr().err


def test_interrupted_run_leaves_no_results(real_dir, tmp_path):
    def factory(weights, device):
        def restore(img):
            raise KeyboardInterrupt

        return restore

    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        evaluate_real(real_dir, ["niqe"], out, weights=["input", "m.safetensors"], restorer_factory=factory)
    assert not (out / "results.json").exists() and not (out / "results.md").exists()
    assert not out.exists() or not list(out.rglob("*.tmp*"))


@pytest.mark.parametrize(
    "metrics, message",
    [
        ("musiq", "MUSIQ weights not found"),
        ("psnr", "psnr needs ground truth"),
        ("nope", "unknown metric 'nope'"),
    ],
)
def test_cli_metric_errors_are_one_line_and_write_nothing(real_dir, tmp_path, capsys, monkeypatch, metrics, message):
    monkeypatch.delenv("D2TURB_MUSIQ_WEIGHTS", raising=False)
    monkeypatch.setenv("D2TURB_CACHE_DIR", str(tmp_path / "empty_cache"))  # a user's cached weights must not matter
    out = tmp_path / "out"
    assert main(["evaluate", "--real", str(real_dir), "--metrics", metrics, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and err.count("\n") == 1
    assert not out.exists()


def test_cli_input_errors(tmp_path, capsys):
    assert main(["evaluate", "--real", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    assert "not a directory" in capsys.readouterr().err
    small = tmp_path / "small"
    write_image(small / "tiny.png", torch.rand(3, 40, 40))
    assert main(["evaluate", "--real", str(small), "--metrics", "niqe", "--out", str(tmp_path / "o")]) == 2
    assert "tiny.png" in capsys.readouterr().err
    assert main(["evaluate", "--data", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "--data needs --weights" in capsys.readouterr().err
    with pytest.raises(D2TurbError, match="no images"):
        (tmp_path / "empty").mkdir()
        evaluate_real(tmp_path / "empty", ["niqe"], tmp_path / "o")


def test_cli_data_dispatches_to_synthetic_evaluator(tmp_path, monkeypatch):
    calls = []
    fake = types.ModuleType("d2turb.eval.synthetic")
    fake.evaluate_synthetic = lambda *a, **k: calls.append((a, k)) or {}
    monkeypatch.setitem(sys.modules, "d2turb.eval.synthetic", fake)
    rc = main(
        [
            "evaluate",
            "--data",
            "ds",
            "--weights",
            "input",
            "m.safetensors",
            "--out",
            str(tmp_path),
            "--max-samples",
            "3",
            "--lpips-weights",
            "lin.pth",
            "--lpips-backbone",
            "alexnet.pth",
        ]
    )
    assert rc == 0
    assert calls[-1] == (
        (["input", "m.safetensors"], "ds", str(tmp_path)),
        {
            "device": "cpu",
            "metrics": None,
            "max_samples": 3,
            "lpips_weights": "lin.pth",
            "lpips_backbone": "alexnet.pth",
            "fail_fast": False,
            "on_skip": print_error,
        },
    )
    assert (
        main(["evaluate", "--data", "ds", "--weights", "input", "--metrics", "PSNR, ssim", "--out", str(tmp_path)]) == 0
    )
    assert calls[-1][1]["metrics"] == ("psnr", "ssim") and calls[-1][1]["lpips_weights"] is None


def test_videos_beside_the_images_are_named_not_skipped_silently(tmp_path, capsys):
    """`evaluate --real --recursive` on a folder holding videos: each video gets one note line (and an entry in
    results.json) saying why it is not scored and how to score its frames; the images are scored as before."""
    real = tmp_path / "real"
    rng = np.random.default_rng(0)
    for rel in ("a.png", "clip/f0.png"):
        (real / rel).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(rng.integers(0, 256, (40, 48, 3), dtype=np.uint8)).save(real / rel)
    (real / "clip" / "take1.mp4").write_bytes(b"\x00" * 64)  # not decoded: named only
    (real / "take2.MOV").write_bytes(b"\x00" * 64)
    (real / ".hidden.mp4").write_bytes(b"\x00" * 64)
    argv = ["evaluate", "--real", str(real), "--recursive", "--metrics", "piqe", "--out", str(tmp_path / "o")]
    assert main(argv) == 0
    notes = [line for line in capsys.readouterr().err.splitlines() if line.startswith("note: ")]
    assert len(notes) == 2
    assert notes[0].startswith("note: clip/take1.mp4: not scored") and notes[1].startswith("note: take2.MOV:")
    assert all("d2turb restore" in n for n in notes)
    results = json.loads((tmp_path / "o" / "results.json").read_text())
    assert [e["file"] for e in results["not_scored"]] == ["clip/take1.mp4", "take2.MOV"]
    assert results["images"] == ["a.png", "clip/f0.png"] and results["skipped"] == []
    # a folder of videos only: the error line says so
    only = tmp_path / "only"
    only.mkdir()
    (only / "v.mp4").write_bytes(b"\x00" * 64)
    assert main(["evaluate", "--real", str(only), "--metrics", "piqe", "--out", str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and "no images found" in err and "1 video file" in err


def test_run_folders_weights_are_named_by_their_config_model_and_folder(tmp_path):
    """Every run folder calls its weights model.safetensors: the tables name them by the model in the file's
    config and the folder (two runs stay apart), a file with its own name keeps it."""
    from _tiny_models import TINY_NAFNET as tiny

    from d2turb.eval.labels import weights_label
    from d2turb.models import create_model, save_pretrained

    a = save_pretrained(create_model("nafnet", **tiny), tmp_path / "run-a" / "model.safetensors")
    b = save_pretrained(create_model("nafnet", **tiny), tmp_path / "run-b" / "best.safetensors")
    own = save_pretrained(create_model("nafnet", **tiny), tmp_path / "run-a" / "sharp.safetensors")
    assert weights_label(a) == "nafnet (run-a)" and weights_label(b) == "nafnet (run-b)"
    assert weights_label(own) == "sharp" and weights_label("input") == "input"
    assert weights_label("d2turb-nafnet") == "d2turb-nafnet"
    assert weights_label(tmp_path / "gone" / "model.safetensors") == "gone/model"  # unreadable: folder/stem


def test_evaluate_real_folder_with_bad_files_lists_them(tmp_path, capsys, astronaut):
    folder = tmp_path / "real"
    write_image(folder / "a.png", astronaut[0, :, :192, :160])
    write_image(folder / "b.png", astronaut[0, :, 40:, 30:])
    (folder / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\nno")
    png_bomb(folder / "bomb.png")
    out = tmp_path / "out"
    rc, _, err = run_cli(capsys, ["evaluate", "--real", str(folder), "--metrics", "piqe", "--out", str(out)])
    assert rc == 1
    lines = error_lines(err)
    assert len(lines) == 2 and "bomb.png" in lines[0] and "corrupt.png" in lines[1]
    results = json.loads((out / "results.json").read_text())
    assert results["images"] == ["a.png", "b.png"]
    assert [s["file"] for s in results["skipped"]] == ["bomb.png", "corrupt.png"]
    assert set(results["piqe"]["per_image"]) == {"a.png", "b.png"}
    assert "corrupt.png" in (out / "results.md").read_text()
