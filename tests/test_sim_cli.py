"""`d2turb simulate` and `d2turb demo` end to end."""

import json

import numpy as np
import pytest
import torch
from PIL import Image

from d2turb.cli import main
from d2turb.io import read_image
from d2turb.ops import warp


@pytest.fixture
def small_png(tmp_path):
    rng = np.random.default_rng(0)
    arr = (rng.random((36, 52, 3)) * 255).astype(np.uint8)
    path = tmp_path / "in" / "scene.png"
    path.parent.mkdir()
    Image.fromarray(arr).save(path)
    return path


def test_simulate_writes_outputs_and_meta(small_png, tmp_path):
    out = tmp_path / "out"
    assert main(["simulate", str(small_png), "--out", str(out), "--dr0", "2.5", "--seed", "4", "--save-flow"]) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == ["scene_flow.npy", "scene_meta.json", "scene_tilt.png", "scene_turb.png"]
    meta = json.loads((out / "scene_meta.json").read_text())
    for key in ("dr0", "aperture_m", "wavelength_m", "path_length_m", "ifov_rad", "offset_s", "modulation", "seed"):
        assert key in meta
    assert meta["dr0"] == 2.5 and meta["seed"] == 4 and meta["bin"] == "medium"
    assert meta["ifov_rad"] == pytest.approx(525e-9 / 0.2)
    flow = np.load(out / "scene_flow.npy")
    assert flow.dtype == np.float32 and flow.shape == (2, 36, 52)
    # the saved flow reproduces the saved tilt image: tilt = clean(x + flow)
    clean = read_image(small_png)[None]
    tilt = warp(clean, torch.from_numpy(flow)[None])[0]
    assert (tilt - read_image(out / "scene_tilt.png")).abs().max() <= 1 / 255 + 1e-6
    # same seed → same result
    out2 = tmp_path / "out2"
    assert main(["simulate", str(small_png), "--out", str(out2), "--dr0", "2.5", "--seed", "4"]) == 0
    assert (out2 / "scene_turb.png").read_bytes() == (out / "scene_turb.png").read_bytes()


def test_simulate_with_depth_file_and_range(small_png, tmp_path):
    depth = np.zeros((36, 52), dtype=np.float32)
    depth[:, 26:] = 1.0
    depth_path = tmp_path / "scene_depth.npy"
    np.save(depth_path, depth + 1.0)  # metric-like values, normalised by the loader (far = 1)
    out = tmp_path / "out"
    assert (
        main(
            [
                "simulate",
                str(small_png.parent),
                "--out",
                str(out),
                "--dr0-range",
                "1",
                "5",
                "--depth",
                str(depth_path),
                "--modulation",
                "power",
                "--save-flow",
            ]
        )
        == 0
    )
    meta = json.loads((out / "scene_meta.json").read_text())
    assert 1 <= meta["dr0"] <= 5 and meta["modulation"] == "power"
    flow = np.load(out / "scene_flow.npy")
    assert np.abs(flow[:, :, :26]).max() == 0.0  # near half: M = 0
    assert np.abs(flow[:, :, 26:]).max() > 0.0


def test_simulate_refuses_bad_image(tmp_path, capsys):
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\nnot really a png")
    out = tmp_path / "out"
    assert main(["simulate", str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "broken.png" in err[0]
    assert not out.exists() or not any(out.iterdir())


def test_simulate_refuses_bad_parameters(small_png, tmp_path, capsys):
    assert main(["simulate", str(small_png), "--out", str(tmp_path / "o"), "--aperture", "-1"]) == 2
    assert "aperture_m" in capsys.readouterr().err


def test_demo_without_a_model_writes_the_simulation_and_the_clip(tmp_path, monkeypatch):
    """--weights none: the simulation and the clip restoration, no single-frame model (the full run with the shipped
    model: tests/test_demo.py). A 4-frame clip keeps this quick."""
    from d2turb.commands import demo

    monkeypatch.setattr(demo, "CLIP_FRAMES", 4)
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--weights", "none"]) == 0
    assert (out / "astronaut_strong_turb.png").is_file() and (out / "coffee_depth.png").is_file()
    assert not list(out.glob("*_restored.png")) and not list(out.glob("clip_*_model.png"))
    assert sorted(p.name for p in out.glob("clip_strong_*")) == [
        f"clip_strong_{t:02d}_{k}.png" for t in (0, 2) for k in ("clip", "input")
    ]
    meta = json.loads((out / "demo_meta.json").read_text())
    assert meta["levels"] == {"weak": 1.5, "medium": 3.0, "strong": 4.5} and "restoration" not in meta
    assert max(Image.open(out / "demo.png").size) <= 2000


def test_demo_restores_with_given_weights(tmp_path, tiny_d2turb_weights, monkeypatch):
    from d2turb.commands import demo

    monkeypatch.setattr(demo, "CLIP_FRAMES", 4)
    out = tmp_path / "demo"  # tiny D²Turb weights with a non-zero predicted flow (conftest)
    assert main(["demo", "--out", str(out), "--weights", str(tiny_d2turb_weights)]) == 0
    table = json.loads((out / "demo_meta.json").read_text())["restoration"]["table"]
    assert sorted(table) == ["medium", "strong", "weak"]
    for row in table.values():
        assert row["epe_zero_flow_px"] > 0 and row["epe_px"] != row["epe_zero_flow_px"]
    assert "| strong | 4.5 |" in (out / "demo_results.md").read_text()
    assert (out / "chart_medium_restored.png").is_file() and (out / "clip_weak_00_model.png").is_file()
