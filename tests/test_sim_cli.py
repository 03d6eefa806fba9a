"""`d2turb simulate` and `d2turb demo` end to end."""

import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from hostile_input import CHILD_ENV, bad_files, error_lines, make_dataset_args, one_error_line, rgb, run_cli, run_d2turb
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
    assert names == ["scene_fwd_flow_px.npy", "scene_meta.json", "scene_tilt.png", "scene_turb.png"]
    meta = json.loads((out / "scene_meta.json").read_text())
    for key in ("dr0", "aperture_m", "wavelength_m", "path_length_m", "ifov_rad", "offset_s", "modulation", "seed"):
        assert key in meta
    assert meta["dr0"] == 2.5 and meta["seed"] == 4 and meta["bin"] == "medium"
    assert meta["ifov_rad"] == pytest.approx(525e-9 / 0.2)
    flow = np.load(out / "scene_fwd_flow_px.npy")
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
    flow = np.load(out / "scene_fwd_flow_px.npy")
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


@pytest.mark.parametrize("size", [(3, 200), (5, 128)])
def test_simulate_a_few_pixels_high_exits_normally(size, tmp_path):
    image = rgb(tmp_path / "strip.png", *size)
    proc = run_d2turb("simulate", image, "--out", tmp_path / "out")
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-2000:])  # a signal would be negative
    assert Image.open(tmp_path / "out" / "strip_turb.png").size == (size[1], size[0])


def test_every_fft_of_the_simulator_gets_a_contiguous_tensor(tmp_path, monkeypatch, capsys):
    """The abort came from torch.fft.fft2 on the permuted view einsum returns: every FFT input in d2turb.sim
    must be contiguous (checked on the calls themselves, in simulate and simulate-video)."""
    seen = []
    for name in ("fft2", "ifft2", "rfft2", "irfft2", "fftn", "ifftn", "rfftn", "irfftn"):
        original = getattr(torch.fft, name)

        def spy(x, *args, _original=original, _name=name, **kwargs):
            seen.append((_name, tuple(x.shape), x.is_contiguous()))
            return _original(x, *args, **kwargs)

        monkeypatch.setattr(torch.fft, name, spy)
    image = rgb(tmp_path / "strip.png", 3, 200)
    assert main(["simulate", str(image), "--out", str(tmp_path / "a")]) == 0
    image = rgb(tmp_path / "b.png", 24, 40)
    assert main(["simulate", str(image), str(tmp_path / "strip.png"), "--out", str(tmp_path / "b")]) == 0
    args = ["simulate-video", str(image), "--out", str(tmp_path / "v"), "--frames", "2", "--no-mp4"]
    assert main(args) == 0
    capsys.readouterr()
    assert seen and all(contiguous for _, _, contiguous in seen), [s for s in seen if not s[2]]


def test_simulate_folder_with_bad_files(tmp_path, capsys):
    folder = tmp_path / "in"
    bad = bad_files(folder)
    good = ["g1", "g2", "g3"]
    for i, name in enumerate(good):
        rgb(folder / f"{name}.png", 24, 32 if i < 2 else 20, seed=i)  # two sizes: two batches
    out = tmp_path / "out"
    rc, stdout, err = run_cli(capsys, ["simulate", str(folder), "--out", str(out), "--no-tilt"])
    assert rc == 1
    lines = error_lines(err)
    assert len(lines) == len(bad)
    for name, word in bad.items():
        assert any(name in line and word in line for line in lines), (name, lines)
    assert f"3 of {len(bad) + 3} inputs done, {len(bad)} failed" in err
    assert sorted(p.name for p in out.iterdir()) == sorted(f"{n}_{k}" for n in good for k in ("turb.png", "meta.json"))
    # --fail-fast: the first bad file (sorted order: bomb.png) ends the run in one line
    rc, _, err = run_cli(capsys, ["simulate", str(folder), "--out", str(tmp_path / "ff"), "--fail-fast"])
    assert rc == 2
    one_error_line(err, "bomb.png")


def test_depth_map_of_another_aspect_is_refused(tmp_path, capsys):
    image = rgb(tmp_path / "a.png", 24, 32)
    np.save(tmp_path / "depth.npy", np.ones((24, 24)))
    rc, _, err = run_cli(
        capsys, ["simulate", str(image), "--out", str(tmp_path / "o"), "--depth", str(tmp_path / "depth.npy")]
    )
    assert rc == 2
    one_error_line(err, "depth.npy", "24x24", "32x24", "aspect")
    assert not (tmp_path / "o").exists()
    np.save(tmp_path / "depth.npy", np.ones((12, 16)))  # same aspect, other resolution: resized
    assert main(["simulate", str(image), "--out", str(tmp_path / "o"), "--depth", str(tmp_path / "depth.npy")]) == 0


def test_simulate_into_its_input_folder_is_refused(tmp_path, capsys):
    folder = tmp_path / "photos"
    rgb(folder / "a.png", 24, 32)
    mine = rgb(folder / "a_tilt.png", 24, 32, seed=5)  # the user's own file, named like an output
    before = mine.read_bytes()
    for argv in (
        ["simulate", str(folder), "--out", str(folder)],
        ["simulate", str(folder / "a.png"), "--out", str(folder)],
        ["simulate", str(folder / "a.png"), "--out", str(folder / "." / "")],
    ):
        rc, _, err = run_cli(capsys, argv)
        assert rc == 2
        one_error_line(err, "--out", "input")
        assert mine.read_bytes() == before and sorted(p.name for p in folder.iterdir()) == ["a.png", "a_tilt.png"]
    rc, _, err = run_cli(capsys, ["restore", str(folder), "--weights", "input", "--out", str(folder)])
    assert rc == 2
    one_error_line(err, "--out", "input")
    assert main(["simulate", str(folder / "a.png"), "--out", str(tmp_path / "out")]) == 0  # elsewhere: fine
    capsys.readouterr()


def test_simulate_video_rerun_with_fewer_frames_leaves_a_consistent_folder(tmp_path, capsys):
    image = rgb(tmp_path / "a.png", 24, 32)
    out = tmp_path / "clip"
    base = ["simulate-video", str(image), "--out", str(out), "--no-mp4"]
    assert main([*base, "--frames", "4", "--save-tilt", "--save-flow"]) == 0
    assert len(list((out / "turb").iterdir())) == 4
    assert main([*base, "--frames", "2"]) == 0
    capsys.readouterr()
    meta = json.loads((out / "meta.json").read_text())
    assert meta["frames"] == 2
    assert sorted(p.name for p in (out / "turb").iterdir()) == ["000000.png", "000001.png"]
    for kind in ("tilt", "fwd_flow_px"):  # not asked for this time: the earlier run's frames would not match turb/
        assert not (out / kind).exists() or not any((out / kind).iterdir())


@pytest.mark.parametrize("ifov", ["1", "1e-9", "1e-3"])
def test_a_pixel_scale_that_cannot_fit_in_memory_is_refused_before_allocating(ifov, tmp_path, capsys):
    """--ifov 1 asked the PSF optics for a petabyte, 1e-9 for 1.2 TB, 1e-3 grew to 15 GB on a 32² image. The
    supported range is 1/4 to 16 Nyquist pixels λ/(2D) (docs/cli.md): 6.56e-07 to 4.2e-05 rad at D = 0.1 m,
    λ = 525 nm."""
    image = rgb(tmp_path / "a.png", 32, 32)
    rc, _, err = run_cli(capsys, ["simulate", str(image), "--out", str(tmp_path / "o"), "--ifov", ifov])
    assert rc == 2
    one_error_line(err, "--ifov", "6.56e-07", "4.2e-05")
    argv = make_dataset_args(tmp_path, tmp_path / "ds", "--ifov", ifov)
    rc, _, err = run_cli(capsys, argv)
    assert rc == 2
    one_error_line(err, "ifov_rad (--ifov)", "6.56e-07", "4.2e-05")
    assert not (tmp_path / "o").exists() and not (tmp_path / "ds").exists()


def test_the_ends_of_the_pixel_scale_range_simulate(tmp_path, capsys):
    image = rgb(tmp_path / "a.png", 32, 32)
    for ifov in ("6.6e-7", "4.1e-5"):
        assert main(["simulate", str(image), "--out", str(tmp_path / ifov), "--ifov", ifov, "--no-tilt"]) == 0
    capsys.readouterr()


@pytest.mark.parametrize("inherited", ["default", "ignored"])
def test_ctrl_c_during_simulate_stops_cleans_up_and_exits_130(tmp_path, inherited):
    """SIGINT while `simulate` works through 64 images: exit 130 with one `interrupted` line, no temp file left,
    every output it finished complete (turb, tilt and meta of each image), the rest not started. Also when the
    process was started with SIGINT ignored (a script's `cmd &`), which it used to inherit and run to the end."""
    folder, out = tmp_path / "in", tmp_path / "out"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(64):
        Image.fromarray((rng.random((48, 64, 3)) * 255).astype(np.uint8)).save(folder / f"img{i:02d}.png")
    ignore = (lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)) if inherited == "ignored" else None
    cmd = [sys.executable, "-m", "d2turb", "simulate", str(folder), "--out", str(out), "--seed", "1"]
    proc = subprocess.Popen(cmd, env=CHILD_ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, preexec_fn=ignore)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if out.is_dir() and len(list(out.glob("*_meta.json"))) >= 2:
            break
        time.sleep(0.01)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    err = err.decode()
    assert proc.returncode == 130, err
    assert err.strip().splitlines() == ["interrupted"] and "Traceback" not in err
    names = sorted(p.name for p in out.iterdir())
    assert not [n for n in names if n.startswith(".") or ".tmp" in n], names
    done = sorted(n.removesuffix("_meta.json") for n in names if n.endswith("_meta.json"))
    assert 2 <= len(done) < 64
    assert names == sorted(f"{stem}_{kind}" for stem in done for kind in ("meta.json", "tilt.png", "turb.png"))
    for stem in done:
        assert Image.open(out / f"{stem}_turb.png").size == (64, 48)
