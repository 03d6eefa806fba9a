"""`d2turb app` without a browser or gradio: the plain-Python callbacks (d2turb.app.core), their physics, the
command lines they show (run again, they must write the same files), bad input, and the install hint."""

import json
import math
import os
import shlex
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from PIL import Image

from d2turb.app import core
from d2turb.cli import main
from d2turb.defaults import DEFAULT_OVERLAP_PX, DEFAULT_TILE_PX
from d2turb.errors import D2TurbError
from d2turb.sim import TurbulenceParams, derived_quantities

SRC = Path(__file__).resolve().parents[1] / "src"


@pytest.fixture(autouse=True)
def _torch_threads():
    """Overrides conftest's 2 threads: these tensors are tiny, and on a loaded machine each parallel region of a
    second thread waits for a time slice (a 40² tile of the tiny model: 3.8 s with 2 threads, 0.05 s with 1)."""
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(2)


@pytest.fixture
def workspace():
    ws = core.Workspace()
    yield ws
    ws.cleanup()


def _rgb(h, w, seed=0):
    rng = np.random.default_rng(seed)
    base = np.linspace(0, 255, w)[None, :, None] * np.ones((h, 1, 3))
    return np.clip(base + rng.normal(0, 30, (h, w, 3)), 0, 255).astype(np.uint8)


def _reproduce(r, where: Path) -> int:
    """Unpack the page's download, set aside what its commands wrote, run the command lines the page shows there
    (each as a subprocess, ``d2turb`` = this checkout's ``python -m d2turb``, as a user's shell would) and check that
    they write the page's files bit for bit; returns the number of files compared."""
    with zipfile.ZipFile(r.files[0]) as zf:
        zf.extractall(where)
    (folder,) = [p for p in where.iterdir() if p.name != "page"]
    assert (folder / "command.sh").read_text().strip().endswith(r.command)
    argvs = [shlex.split(line) for line in r.command.splitlines()]
    outs = [argv[argv.index("--out") + 1] for argv in argvs]
    for out in outs:
        (where / "page" / out).parent.mkdir(parents=True, exist_ok=True)
        shutil.move(folder / out, where / "page" / out)
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    for argv in argvs:
        assert argv[0] == "d2turb"
        res = subprocess.run(
            [sys.executable, "-m", "d2turb", *argv[1:]], cwd=folder, env=env, capture_output=True, timeout=600
        )
        assert res.returncode == 0, res.stderr.decode()
    return sum(_same_files(folder / out, where / "page" / out) for out in outs)


def _same_files(a: Path, b: Path) -> int:
    names = sorted(str(p.relative_to(a)) for p in a.rglob("*") if p.is_file())
    assert names == sorted(str(p.relative_to(b)) for p in b.rglob("*") if p.is_file())
    for name in names:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    return len(names)


@pytest.fixture
def executed(monkeypatch):
    """The argument lists the page runs, in order (recorded around d2turb.app.jobs.run_command)."""
    import d2turb.app.tabs

    calls = []

    def record(argv, cwd, progress=None):
        calls.append(list(argv))
        return core.run_command(argv, cwd, progress)

    monkeypatch.setattr(d2turb.app.tabs, "run_command", record)
    return calls


# ---- physics of the derived quantities ---------------------------------------------------------------------------
def test_derived_quantities_match_the_formulas_of_physics_md():
    p = TurbulenceParams(aperture_m=0.1, wavelength_m=525e-9, path_length_m=1000.0, dr0=3.0)
    d = derived_quantities(p, mean_modulation=0.5)
    lam, aperture, ifov = 525e-9, 0.1, 525e-9 / 0.2
    # σ_px = sqrt(0.1816)(λ/D)/ifov·(D/r0)^(5/6) (docs/physics.md §2; 0.1816 given to 4 digits)
    assert d["tilt_sigma_px"] == pytest.approx(math.sqrt(0.1816) * (lam / aperture) / ifov * 3 ** (5 / 6), rel=1e-3)
    assert d["tilt_sigma_px"] == pytest.approx(0.852 * 3 ** (5 / 6), rel=1e-3)  # the Nyquist value
    assert d["tilt_sigma_px_mean_m"] == pytest.approx(0.5 * d["tilt_sigma_px"])  # Δ = M·Δ0 (Eq. 5)
    assert d["r0_m"] == pytest.approx(0.1 / 3)
    # constant Cn²: θ0 = 0.314 r0_spherical / L (physics notes §3, 0.314 to 3 digits)
    assert d["theta0_urad"] * 1e-6 == pytest.approx(0.314 * d["r0_m"] / 1000.0, rel=2e-3)
    assert d["theta0_px"] == pytest.approx(d["theta0_urad"] * 1e-6 / ifov)
    assert d["footprint_px"] == pytest.approx(aperture / (ifov * 1000.0))  # D/(ifov·L) = 38.1 px
    assert d["samples_per_lambda_d"] == pytest.approx(2.0) and d["bin"] == "medium"
    # the worked value: Cn² = 1e-14, L = 1 km, λ = 0.5 µm → spherical-wave r0 = 3.64 cm; Cn² comes back
    q = derived_quantities(TurbulenceParams(wavelength_m=500e-9, cn2=1e-14))
    assert q["r0_m"] == pytest.approx(0.0364, abs=5e-5)
    assert q["cn2"] == pytest.approx(1e-14, rel=1e-9)
    # θ0 ∝ L^(-8/5) at fixed Cn² (r0 ∝ L^(-3/5), θ0 ∝ r0/L)
    far = derived_quantities(TurbulenceParams(wavelength_m=500e-9, cn2=1e-14, path_length_m=2000.0))
    assert far["theta0_urad"] / q["theta0_urad"] == pytest.approx(2 ** (-8 / 5), rel=1e-9)


def test_units_typed_in_the_page_give_the_clis_floats():
    assert core.parse_wavelengths_nm("525") == [525e-9]
    assert core.parse_wavelengths_nm("620, 530 460") == [620e-9, 530e-9, 460e-9]
    assert core.parse_wavelengths_nm("0.525e3") == [525e-9]
    for bad in ("", "abc", "500 600", "-5", "nan"):
        with pytest.raises(D2TurbError, match="wavelength"):
            core.parse_wavelengths_nm(bad)
    assert float(core.fmt_float(0.1 + 0.2)) == 0.1 + 0.2
    assert core.safe_stem("-rm -rf.png") == "image_-rm_-rf"  # never read as an option
    assert core.safe_stem("my photo (1).JPG") == "my_photo_1"
    assert core.safe_stem("...") == "image"
    values = core.sim_values(core.SimSettings(dr0=3.0500000000000003, aperture_m=0.30000000000000004), None)
    argv = core.simulate_argv(values, "a.png")
    assert argv[argv.index("--dr0") + 1] == "3.05" and argv[argv.index("--aperture") + 1] == "0.3"


# ---- simulate ----------------------------------------------------------------------------------------------------
def test_simulate_sample_with_prior_depth_is_reproduced_by_its_command_line(workspace, tmp_path, executed):
    s = core.SimSettings(source="sample", sample="chart", dr0=2.0, depth="prior", seed=5, modulation="power_offset")
    r = core.run_simulation(s, workspace)
    assert r.command == core.command_text(*executed)  # what ran is what the page shows
    assert r.command.startswith("d2turb simulate chart.png --out out --seed 5 --dr0 2.0 --depth prior")
    out = r.run_dir / "out"
    turb = np.asarray(Image.open(r.turb))
    assert turb.shape == (192, 256, 3)  # the demo's sample size
    flow = np.load(out / "chart_fwd_flow_px.npy")
    assert flow.shape == (2, 192, 256) and flow.dtype == np.float32
    assert r.flow_scale_px == pytest.approx(float(np.linalg.norm(flow, axis=0).max()), rel=1e-6)
    # M shown = Eq. 3 applied to the depth shown: ((1 − s)d̃ + s)^(3/5), s = 0.5 (both pictures 8-bit)
    d = np.asarray(Image.open(r.depth), dtype=np.float64) / 255
    m = np.asarray(Image.open(r.modulation), dtype=np.float64) / 255
    assert np.abs(m - (0.5 * d + 0.5) ** 0.6).max() <= 1.5 / 255
    assert r.derived["mean_modulation"] == pytest.approx(m.mean(), abs=1 / 255)
    assert r.derived["dr0"] == 2.0 and r.derived["bin"] == "weak"
    # the flow is the tilt field scaled by M: its spread sits near σ·mean(M) (one 192×256 field, loose bound)
    assert 0.3 < flow.std() / r.derived["tilt_sigma_px_mean_m"] < 2.0
    # downloads: the zip, the four CLI outputs, the script
    assert [p.name for p in r.files] == [
        "d2turb_simulate_chart.zip",
        "chart_turb.png",
        "chart_tilt.png",
        "chart_fwd_flow_px.npy",
        "chart_meta.json",
        "command.sh",
    ]
    assert _reproduce(r, tmp_path / "again") == 4  # bit for bit, meta.json included


def test_simulate_upload_with_depth_map_cn2_rgb_and_ifov(workspace, tmp_path):
    img = tmp_path / "street view.png"
    Image.fromarray(_rgb(48, 64)).save(img)
    depth = tmp_path / "depth.npy"
    np.save(depth, np.tile(np.linspace(1, 4, 48)[:, None], (1, 64)))  # disparity: top far, bottom near
    s = core.SimSettings(
        source="upload",
        upload=str(img),
        strength="Cn²",
        cn2=3e-15,
        wavelength_nm="620 530 460",
        ifov_urad=4.0,
        depth="upload",
        depth_upload=str(depth),
        disparity=True,
        modulation="linear",
        seed=1,
    )
    r = core.run_simulation(s, workspace)
    assert r.command == (
        "d2turb simulate street_view.png --out out --seed 1 --cn2 3e-15 --depth street_view_depthmap.npy "
        "--disparity --aperture 0.1 --wavelength 6.2e-07 5.3e-07 4.6e-07 --path-length 1000.0 --ifov 4e-06 "
        "--modulation linear --offset 0.5 --save-flow"
    )
    assert r.warnings == []
    meta = json.loads((r.run_dir / "out" / "street_view_meta.json").read_text())
    assert meta["cn2"] == 3e-15 and meta["ifov_rad"] == 4e-06
    assert r.derived["dr0"] == pytest.approx(meta["dr0"])
    # linear M = d̃ and disparity is inverted: the bottom row (largest disparity) is nearest, M = 0
    m = np.asarray(Image.open(r.modulation), dtype=np.float64) / 255
    assert m[0].min() == 1.0 and m[-1].max() == 0.0
    assert meta["input"] == "street_view.png" and meta["depth"] == "street_view_depthmap.npy"  # run in the folder
    assert _reproduce(r, tmp_path / "again") == 4


def test_simulate_bad_input_gives_one_line_messages(workspace, tmp_path):
    good = tmp_path / "ok.png"
    Image.fromarray(_rgb(40, 40)).save(good)
    text = tmp_path / "notes.png"
    text.write_text("not an image")
    colour = tmp_path / "colour.png"
    Image.fromarray(_rgb(40, 40, seed=3)).save(colour)
    nan = tmp_path / "nan.npy"
    np.save(nan, np.full((40, 40), np.nan))
    cases = [
        (dict(source="upload", upload=str(text)), "notes.png: cannot read image"),
        (dict(source="upload", upload=str(tmp_path / "x.txt")), "not an image file type"),
        (dict(source="upload", upload=None), "upload an image first"),
        (dict(source="upload", upload=str(good), depth="upload", depth_upload=str(colour)), "colour-mapped"),
        (dict(source="upload", upload=str(good), depth="upload", depth_upload=str(nan)), "NaN"),
        (dict(source="upload", upload=str(good), depth="upload", depth_upload=None), "upload a depth map first"),
        (dict(strength="Cn²", cn2=1e-12), "beyond the supported range"),
        (dict(aperture_m=-1), "aperture must be positive"),
        (dict(wavelength_nm="green"), "wavelength"),
        (dict(sample="lena"), "unknown sample"),
        (dict(seed=-1), "seed must be a whole number"),
        (dict(ifov_urad=-2), "pixel IFOV (µrad) must be positive"),
    ]
    for kwargs, expected in cases:
        with pytest.raises(D2TurbError) as info:
            core.run_simulation(core.SimSettings(**kwargs), workspace)
        message = str(info.value)
        assert expected in message and "\n" not in message, (kwargs, message)
    with pytest.raises(D2TurbError, match=r"40x40 is too large for the app"):
        core.run_simulation(core.SimSettings(source="upload", upload=str(good)), workspace, core.Limits(sim_pixels=999))


def test_depth_map_of_another_aspect_ratio_is_refused(workspace, tmp_path):
    img = tmp_path / "a.png"
    Image.fromarray(_rgb(40, 60)).save(img)
    depth = tmp_path / "d.png"
    Image.fromarray(np.tile(np.arange(40, dtype=np.uint8)[:, None] * 6, (1, 40))).save(depth)
    with pytest.raises(D2TurbError, match="aspect ratios differ") as info:  # the rule of `d2turb simulate`
        core.run_simulation(
            core.SimSettings(source="upload", upload=str(img), depth="upload", depth_upload=str(depth)), workspace
        )
    assert "\n" not in str(info.value)


# ---- restore -----------------------------------------------------------------------------------------------------
def test_restore_identity_image_and_video(workspace, tmp_path):
    img = tmp_path / "scene.png"
    Image.fromarray(_rgb(200, 240)).save(img)
    r = core.run_restore(str(img), "input", workspace)
    tiles = f"--tile {DEFAULT_TILE_PX} --overlap {DEFAULT_OVERLAP_PX}"  # the command line's defaults, written out
    assert r.command == f"d2turb restore scene.png --weights input --out out {tiles} --save-flow"
    np.testing.assert_array_equal(np.asarray(Image.open(r.after)), _rgb(200, 240))  # identity: output = input
    assert isinstance(r.niqe["input"], float) and r.niqe["input"] == r.niqe["restored"]
    assert not np.load(r.files[2]).any() and r.flow_scale_px == 0
    frames = [Image.fromarray(_rgb(24, 32, seed=i)) for i in range(3)]
    gif = tmp_path / "clip.gif"
    frames[0].save(gif, save_all=True, append_images=frames[1:], duration=50, loop=0)
    bars = []
    v = core.run_restore(str(gif), "input", workspace, progress=lambda fraction, desc: bars.append((fraction, desc)))
    assert v.frames == 3 and "3 frames" in v.notes[0]
    assert bars[-1] == (1.0, "clip.gif")  # the command's tqdm bar (its stderr) drives the page's
    assert isinstance(v.niqe["input"], str) and v.niqe["input"].startswith("n/a")  # 24x32 has no 96x96 block
    with zipfile.ZipFile(v.files[0]) as zf:
        restored = sorted(n for n in zf.namelist() if n.endswith("_restored.png"))
    assert [Path(n).name for n in restored] == [f"clip_{i:06d}_restored.png" for i in range(3)]
    assert _reproduce(v, tmp_path / "again") in (6, 7)  # each frame's restored PNG and flow (and the mp4)
    with pytest.raises(D2TurbError, match="5 frames is more"):  # noqa: PT012
        frames[0].save(gif, save_all=True, append_images=frames[1:] * 2, duration=50, loop=0)
        core.run_restore(str(gif), "input", workspace, limits=core.Limits(video_frames=3))


def test_restore_tiny_model_tiled_is_reproduced_by_its_command_line(workspace, tiny_d2turb_weights, tmp_path, executed):
    img = tmp_path / "far.png"
    Image.fromarray(_rgb(56, 72)).save(img)
    r = core.run_restore(str(img), str(tiny_d2turb_weights), workspace, tile=40, overlap=16)  # 2 x 2 tiles
    assert f"--weights {tiny_d2turb_weights} --out out --tile 40 --overlap 16" in r.command
    assert np.asarray(Image.open(r.after)).shape == (56, 72, 3)
    flow = np.load(r.files[2])
    assert flow.shape == (2, 56, 72) and r.flow_scale_px > 0.1
    assert r.command == core.command_text(*executed)
    assert _reproduce(r, tmp_path / "again") == 2


def test_weights_choices_follow_resolve_weights(tmp_path, monkeypatch):
    import d2turb.models.hub
    from d2turb.models.hub import resolve_weights

    a, b, cache, package = tmp_path / "a", tmp_path / "b", tmp_path / "cache", tmp_path / "package"
    shipped = package / "resources" / "weights"
    monkeypatch.setattr(d2turb.models.hub, "resources", SimpleNamespace(files=lambda name: package))
    monkeypatch.setenv("D2TURB_WEIGHTS_DIR", f"{a}:{b}")
    monkeypatch.setenv("D2TURB_CACHE_DIR", str(cache))
    assert core.weights_choices() == [("input", None)] and core.default_weights(core.weights_choices()) == "input"
    for folder, names in ((a, ["m1"]), (b, ["m1", "m2", "bad name"]), (cache / "weights", ["m3"])):
        folder.mkdir(parents=True)
        for n in names:
            (folder / f"{n}.safetensors").write_bytes(b"")
    assert core.default_weights(core.weights_choices()) == "m1"  # nothing shipped: the first found
    shipped.mkdir(parents=True)
    (shipped / "d2turb-small.safetensors").write_bytes(b"")
    choices = core.weights_choices()
    assert choices[0] == ("input", None)
    expected = [("m1", a), ("m2", b), ("m3", cache / "weights"), ("d2turb-small", shipped)]
    assert [(n, p.parent) for n, p in choices[1:]] == expected
    for name, path in choices[1:]:
        assert resolve_weights(name) == path
    assert core.shipped_weights_dir() == shipped and core.default_weights(choices) == "d2turb-small"


def test_restore_bad_input_gives_one_line_messages(workspace, tmp_path):
    img = tmp_path / "ok.png"
    Image.fromarray(_rgb(30, 30)).save(img)
    junk = tmp_path / "clip.mp4"
    junk.write_bytes(b"\x00" * 64)
    cases = [
        ((None, "input"), "upload an image"),
        ((str(img), "no-such-weights"), "weights 'no-such-weights' not found"),
        ((str(img), str(tmp_path / "w.pt")), "only .safetensors"),
        ((str(tmp_path / "gone.png"), "input"), "upload it again"),
        ((str(junk), "input"), "cannot read video"),
    ]
    for args, expected in cases:
        with pytest.raises(D2TurbError) as info:
            core.run_restore(*args, workspace)
        assert expected in str(info.value) and "\n" not in str(info.value), (args, str(info.value))
    with pytest.raises(D2TurbError, match="too large for the app"):
        core.run_restore(str(img), "input", workspace, limits=core.Limits(restore_pixels=500))


def test_an_error_of_the_command_is_one_line_in_the_page(tmp_path):
    """A job's command that fails (here: a missing input, a usage error) gives its own ``error:`` line as the page's
    one-line message."""
    with pytest.raises(D2TurbError) as info:
        core.run_command(["simulate", "missing.png", "--out", "out"], tmp_path)
    assert str(info.value) == "missing.png: no such file or directory"
    with pytest.raises(D2TurbError, match=r"^argument --dr0: invalid float value: 'x'"):
        core.run_command(["simulate", "a.png", "--out", "out", "--dr0", "x"], tmp_path)


# ---- the command and the install -----------------------------------------------------------------------------------
def test_base_install_does_not_pull_the_app_dependencies_and_the_command_says_how_to_install():
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    meta = tomllib.loads((SRC.parent / "pyproject.toml").read_text())["project"]
    assert not any(dep.lower().startswith(("gradio", "fastapi", "uvicorn")) for dep in meta["dependencies"])
    assert meta["optional-dependencies"]["app"] == ["gradio>=5"]
    # the command line and the app's plain-Python part never import gradio; with gradio missing, `d2turb app`
    # prints one line and exits with 2 (one subprocess: importing torch is slow on a loaded machine)
    code = (
        "import sys; from d2turb.cli import build_parser, main; build_parser(); import d2turb.app.core; "
        "assert 'gradio' not in sys.modules, 'gradio imported'; sys.modules['gradio'] = None; sys.exit(main(['app']))"
    )
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip().splitlines() == [
        "error: d2turb app needs the app extra: pip install 'd2turb[app]' (from a checkout: pip install -e '.[app]')"
    ]
    from d2turb.cli import build_parser

    assert build_parser().parse_args(["app"]).host == "127.0.0.1"  # this machine only, unless asked


def test_a_folder_named_gradio_is_not_the_extra(tmp_path, monkeypatch, capsys):
    """Gradio's own cache is /tmp/gradio: started in /tmp without the extra, `import gradio` finds that folder."""
    import importlib.util

    spec = importlib.util.find_spec("gradio")
    if spec is not None and spec.origin not in (None, "namespace"):
        pytest.skip("gradio is installed")
    (tmp_path / "gradio").mkdir()
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "gradio", raising=False)
    for name in ("GRADIO_TEMP_DIR", "GRADIO_ANALYTICS_ENABLED", "MPLCONFIGDIR"):
        monkeypatch.delenv(name, raising=False)
    assert importlib.util.find_spec("gradio") is not None  # the folder is importable as a namespace package
    assert main(["app"]) == 2
    assert (
        capsys.readouterr().err.strip()
        == "error: d2turb app needs the app extra: pip install 'd2turb[app]' (from a checkout: pip install -e '.[app]')"
    )


def test_clip_tab_simulates_from_an_image_and_restores_with_the_known_strength(workspace, tmp_path, executed):
    """An uploaded image becomes a simulated clip at D/r0 = 2 and is restored with that D/r0; the command lines
    reproduce the run (the simulated and the restored frames are byte-identical when run again from the download)."""
    path = tmp_path / "scene.png"
    Image.fromarray(_rgb(48, 56)).save(path)
    r = core.run_clip(str(path), workspace, temporal=4, dr0=2.0)
    assert r.frames == core.CLIP_SIM_FRAMES
    assert r.command == core.command_text(*executed)
    lines = r.command.splitlines()
    assert lines[0].startswith("d2turb simulate-video scene.png --out clip --frames 32 --dr0 2")
    assert lines[1] == "d2turb restore clip/turb --temporal 4 --out out --save-intermediate --dr0 2"
    assert np.asarray(Image.open(r.after)).shape == (48, 56, 3)
    restored = sorted((r.run_dir / "out").glob("*_restored.png"))
    assert len(restored) == 32
    assert _reproduce(r, tmp_path / "again") >= 32 + 32 + 32  # clip/turb frames, restored and deblurred frames


def test_clip_tab_refuses_bad_uploads(workspace, tmp_path):
    with pytest.raises(D2TurbError, match="upload a short video"):
        core.run_clip(None, workspace)
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(D2TurbError, match="not a video or image"):
        core.run_clip(str(tmp_path / "notes.txt"), workspace)
    with pytest.raises(D2TurbError, match="window"):
        core.run_clip(str(tmp_path / "notes.txt"), workspace, temporal=1)


def test_niqe_on_the_page_comes_with_its_caveat():
    """The page's NIQE table says what the score is worth (docs/metrics.md), not only the numbers."""
    text = core.niqe_markdown({"input": 5.25, "restored": "n/a (too small)"})
    assert "| input | 5.250 |" in text and "| restored | n/a (too small) |" in text
    assert "not proof of restoration" in text and "docs/metrics.md" in text


def test_clip_tab_counts_the_frames_of_containers_that_do_not_store_them(workspace, tmp_path):
    """An mkv (no frame count in the container) is counted by decoding: the frame limit applies and the middle
    frame is shown; without a D/r0 the command says --deblur none, as the page says."""
    pytest.importorskip("av")
    iio = pytest.importorskip("imageio.v3")
    frames = np.stack([_rgb(32, 40, seed=i) for i in range(6)])
    iio.imwrite(tmp_path / "clip.mkv", frames, plugin="pyav", codec="libx264", fps=10)
    with pytest.raises(D2TurbError, match="more than the app takes"):
        core.run_clip(str(tmp_path / "clip.mkv"), workspace, temporal=3, limits=core.Limits(video_frames=5))
    r = core.run_clip(str(tmp_path / "clip.mkv"), workspace, temporal=3)
    assert r.frames == 6 and r.command.endswith("--deblur none")
    assert np.asarray(Image.open(r.after)).shape == (32, 40, 3)
    assert _reproduce(r, tmp_path / "again") >= 6  # the restored frames of the video, bit for bit
