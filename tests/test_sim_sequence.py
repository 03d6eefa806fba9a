"""Turbulence in time (issue 14): frozen-flow sequences against theory, and the sequence API.

Physics checks (docs/simulator.md, "Sequences"): (a) a pixel's tilt decorrelates in time like two image
points separated along the wind, I0 ± I2 at s = v·Δt/(D(1 − z/L)), path-weighted; (b) every frame has
the single-frame tilt and Zernike statistics; (c) the mean of many frames' PSFs is the long-exposure OTF;
(d) boiling 1 gives uncorrelated frames, wind 0 and boiling 0 identical ones.
"""

import math

import numpy as np
import pytest
import torch

from d2turb.errors import D2TurbError
from d2turb.sim import Optics, Simulator, TurbulenceParams
from d2turb.sim.fields import PlaneWaveGrid
from d2turb.sim.psf import PupilPSF
from d2turb.sim.sequence import FrozenFlow, wind_speeds
from d2turb.sim.zernike import noll_covariance

# physics.md §2: one layer's (I0 ± I2)/I0(0) table
TABLE_S = [0.25, 0.5, 1, 2, 5, 10]
TABLE_PERP = [0.974, 0.912, 0.780, 0.630, 0.467, 0.371]
TABLE_PAR = [0.926, 0.772, 0.558, 0.428, 0.312, 0.247]


def _pixel_series(params, batch, frames, fps, wind, wind_dir, boil=0.0, seed=0, probe=None, chunk=100):
    """(batch, frames, 2) unit tilt at one pixel of `batch` independent sequences (None for no frames), and
    ``probe(state)`` of every sequence's state after its frames, concatenated over the sequences (None without
    a probe). The sequences come `chunk` at a time from one generator: a path state's plane waves take ~1 MB
    a sequence while they are drawn, so 500 at once would take 0.6 GB."""
    gen = torch.Generator().manual_seed(seed)
    sim = Simulator(params)
    series, probed = [], []
    for start in range(0, batch, chunk):
        n = min(chunk, batch - start)
        state = FrozenFlow(sim, n, 1, 1, fps, wind, wind_dir, boil, gen, high_waves=0)
        out = []
        for _ in range(frames):
            out.append(state.tilt(n, 1, 1)[:, :, 0, 0].double())
            state.advance(gen)
        if out:
            series.append(torch.stack(out, 1).numpy())
        if probe is not None:
            probed.append(probe(state))
        del state
    return (np.concatenate(series) if series else None), (np.concatenate(probed) if probed else None)


def _lag_covariance(lags):
    """A probe of :func:`_pixel_series`: each sequence's tilt covariance at the same pixel ``lags`` frames
    apart, given its plane waves (``tilt_covariance``), (B, N, 2, 2)."""
    lags = torch.as_tensor(lags, dtype=torch.float64)
    return lambda state: state.tilt_covariance(np.zeros((len(lags), 2)), lags).numpy()


def _temporal_correlation(series, wind_dir, lags, n_batches=10):
    """Structure-function estimates 1 − ½E[(t(τ+T) − t(τ))²] of the components parallel and perpendicular
    to the wind, and their standard errors from batch means over the sequences."""
    phi = math.radians(wind_dir)
    par = series[..., 0] * math.cos(phi) + series[..., 1] * math.sin(phi)
    perp = -series[..., 0] * math.sin(phi) + series[..., 1] * math.cos(phi)
    out = {}
    for name, comp in (("par", par), ("perp", perp)):
        est = np.array(
            [
                [1 - 0.5 * ((c[:, lag:] - c[:, :-lag]) ** 2).mean() for lag in lags]
                for c in np.array_split(comp, n_batches)
            ]
        )
        out[name] = (est.mean(0), est.std(0, ddof=1) / math.sqrt(n_batches))
    return out


def _wave_correlation(cov, wind_dir):
    """Temporal correlation given the sequences' plane waves (their covariances (B, N, 2, 2) from
    :func:`_lag_covariance`), parallel and perpendicular to the wind: mean over sequences and its standard
    error."""
    phi = math.radians(wind_dir)
    rot = np.array([[math.cos(phi), math.sin(phi)], [-math.sin(phi), math.cos(phi)]])
    cov = rot @ cov @ rot.T  # (B, N, 2, 2) in (parallel, perpendicular) axes
    n = len(cov)
    return {
        name: (cov[:, :, i, i].mean(0), cov[:, :, i, i].std(0, ddof=1) / math.sqrt(n))
        for name, i in (("par", 0), ("perp", 1))
    }


def test_temporal_correlation_single_layer_matches_table():
    """(a), one layer at z = L/2: the wind moves it by s = v·Δt/(D(1 − z/L)) = 0.25 per frame, so lags of
    1 … 40 frames are s = 0.25 … 10 and the correlation is the physics.md table itself. Given their plane
    waves, 300 sequences (wind at 30°) are within 0.05 of the table at every lag (standard error over
    sequences ≤ 0.005); their frames (11 frames of 600 sequences) give the same at lags 1, 2, 4 (s ≤ 1)
    within 4 SE + 0.01 (SE ≤ 0.006 from 10 batch means)."""
    params = TurbulenceParams(tilt_geometry="layer", layer_z_frac=0.5)
    fps, s_per_frame = 30.0, 0.25
    wind = s_per_frame * params.aperture_m * (1 - 0.5) * fps
    lags = np.array([round(s / s_per_frame) for s in TABLE_S])
    _, cov = _pixel_series(params, 300, 0, fps, wind, 30.0, probe=_lag_covariance(lags))
    waves = _wave_correlation(cov, 30.0)
    series, _ = _pixel_series(params, 600, 11, fps, wind, 30.0, seed=1)
    frames = _temporal_correlation(series, 30.0, lags[:3])
    for name, table in (("par", TABLE_PAR), ("perp", TABLE_PERP)):
        mean, se = waves[name]
        assert se.max() < 0.0125 and np.abs(mean - table).max() < 0.05, (name, mean.round(3), table)
        mean, se = frames[name]
        assert np.all(np.abs(mean - table[:3]) < 4 * se + 0.01), (name, mean.round(3), se.round(4))


@pytest.mark.slow
@pytest.mark.parametrize("wind", [0.75, [0.5, 3.0]])
def test_temporal_correlation_path_matches_theory(wind, published_tilt):
    """(a), constant-Cn² path: the layer at t = z/L moves s = v(t)·Δt/(D(1 − t)) per frame; the oracle is
    the (1 − t)^(5/3)-weighted path average of the published I0 ± I2 integral (uniform wind, and a wind
    rising linearly from 0.5 m/s at the aperture to 3 m/s at the object). Given their plane waves, 200
    sequences (wind at −60°) are within 0.05 at lags 1 … 64 frames (SE ≤ 0.004); their frames (9 frames of
    500 sequences) at lags 1, 2, 4, 8 within 4 SE + 0.01 (SE ≤ 0.012 from 10 batch means)."""
    params = TurbulenceParams()
    fps = 30.0
    lags = np.array([1, 2, 4, 8, 16, 32, 64])

    def s_of_t(t):
        v = wind_speeds(wind, np.full(1, t))[0]
        return lags * v / fps / (params.aperture_m * (1 - t))

    perp, par = published_tilt.path(s_of_t)
    _, cov = _pixel_series(params, 200, 0, fps, wind, -60.0, seed=2, probe=_lag_covariance(lags))
    waves = _wave_correlation(cov, -60.0)
    series, _ = _pixel_series(params, 500, 9, fps, wind, -60.0, seed=3)
    frames = _temporal_correlation(series, -60.0, lags[:4])
    for name, theory in (("par", par), ("perp", perp)):
        mean, se = waves[name]
        assert se.max() < 0.0125 and np.abs(mean - theory).max() < 0.05, (name, mean.round(3), theory.round(3))
        mean, se = frames[name]
        assert np.all(np.abs(mean - theory[:4]) < 4 * se + 0.01), (name, mean.round(3), se.round(4))


@pytest.mark.slow
def test_every_frame_has_single_frame_statistics():
    """(b) D/r0 = 2, boiling 0.3, a fast wind: a2 … a11 at every pixel of 8×8 frames of 200 sequences ×
    12 frames. The path is 5000 km long (D/r0 given, so only the pixel spacing changes): neighbouring
    pixels sample nearly independent higher orders and weakly correlated tilt. Pooled over frames,
    var(a2 … a11), cov(a2, a8), cov(a4, a11) within 5 % of Noll (measured ≤ 1.9 %; standard errors from
    10 batch means of 20 sequences: 0.4–1.5 % for the variances, ≤ 1.4 % for the covariances); every
    single frame's var(a2), var(a3), var(a4) within 4 SE of Noll (SE 1.3–2.5 %, measured ≤ 4.2 %) and
    frame 0 ≈ frame 11 (no drift from the wind or boiling)."""
    dr0, b, frames, n = 2.0, 200, 12, 8
    sim = Simulator(TurbulenceParams(dr0=dr0, path_length_m=5e6))
    gen = torch.Generator().manual_seed(7)
    chunk = 50  # sequences drawn at a time (one generator): all 200 at once take ~1 GB
    d = torch.full((chunk,), dr0, dtype=torch.float64)
    a = []
    for _ in range(b // chunk):
        state = FrozenFlow(sim, chunk, n, n, fps=30.0, wind=10.0, wind_dir=15.0, boil=0.3, generator=gen)
        coeffs = []
        for _ in range(frames):
            tilt = sim.tilt_fields(chunk, n, n, d, unit=state.tilt(chunk, n, n))
            high = sim.high_fields(tilt, d, (1.0, 1.0), unit=state.high(n, n, (1.0, 1.0)))
            coeffs.append(torch.cat([tilt, high], 1).double().flatten(2).transpose(1, 2).numpy())  # (B, 64, J-1)
            state.advance(gen)
        a.append(np.stack(coeffs, 1))
        del state, tilt, high
    a = np.concatenate(a)  # (B, frames, pixels, J-1)
    noll = np.asarray(noll_covariance(36)) * dr0 ** (5 / 3)
    batches = np.array_split(a, 10)
    for j, jp in [(j, j) for j in range(2, 12)] + [(2, 8), (4, 11)]:
        est = np.array([(x[..., j - 2] * x[..., jp - 2]).mean() for x in batches])
        se = est.std(ddof=1) / math.sqrt(len(est))
        assert se < 0.025 * abs(noll[j - 2, jp - 2])
        assert est.mean() == pytest.approx(noll[j - 2, jp - 2], rel=0.05), (j, jp)
    for j in (2, 3, 4):
        per_frame = (a[..., j - 2] ** 2).mean(axis=2)  # (B, frames): each sequence's frame variance
        var = per_frame.mean(0)
        se = per_frame.std(0, ddof=1) / math.sqrt(b)
        assert np.all(np.abs(var - noll[j - 2, j - 2]) < 4 * se)
        assert abs(var[0] - var[-1]) < 4 * math.hypot(se[0], se[-1])


def test_mean_of_frames_psfs_is_the_long_exposure_otf():
    """(c) D/r0 = 2, Nyquist pixels: the tilt-included PSFs (a2 … a36 of the sequence's frames) averaged
    over 200 sequences × 15 frames converge to Fried's long-exposure T·H (α = 0), within 0.05 as for
    single frames (MTF standard error ≈ 0.007 from 10 batch means)."""
    d, lam, dr0 = 0.1, 525e-9, 2.0
    sim = Simulator(TurbulenceParams(aperture_m=d, wavelength_m=lam, dr0=dr0))
    b, frames, chunk = 200, 15, 50  # sequences drawn `chunk` at a time (one generator): all at once hold 0.3 GB
    gen = torch.Generator().manual_seed(11)
    optics = PupilPSF(Optics(d, lam, lam / (2 * d)), range(2, 37))
    dv = torch.full((chunk,), dr0, dtype=torch.float64)
    psf = torch.zeros(63, 63, dtype=torch.float64)
    for _ in range(b // chunk):
        state = FrozenFlow(sim, chunk, 2, 2, fps=30.0, wind=10.0, generator=gen)
        for _ in range(frames):
            tilt = sim.tilt_fields(chunk, 2, 2, dv, unit=state.tilt(chunk, 2, 2))
            high = sim.high_fields(tilt, dv, (1.0, 1.0), unit=state.high(2, 2, (1.0, 1.0)))
            psf += optics.psfs(torch.cat([tilt[:, :, 0, 0], high[:, :, 0, 0]], 1).float(), 31)[0].double().sum(0)
            state.advance(gen)
        del state
    psf /= b * frames
    padded = torch.zeros(64, 64, dtype=torch.float64)
    padded[:63, :63] = psf
    otf = torch.fft.fft2(padded).abs().numpy()
    ks = np.array([2, 4, 6, 8, 10, 12, 14, 16])
    mtf = 0.5 * (otf[0, ks] + otf[ks, 0])
    u = 2 * ks / 64  # λν/D
    diffraction = 2 / np.pi * (np.arccos(u) - u * np.sqrt(1 - u * u))
    theory = diffraction * np.exp(-3.44 * (u * dr0) ** (5 / 3))
    assert np.abs(mtf - theory).max() < 0.05


def test_boiling_one_gives_uncorrelated_frames():
    """(d) boil = 1: every wave is redrawn each frame, so consecutive frames are uncorrelated (400 sequences
    × 6 frames: |c| < 4 SE, SE ≈ 0.022 allowing for the waves shared within a sequence) with unit variance;
    the same wind without boiling keeps them correlated (c ≈ 0.8)."""
    params = TurbulenceParams()
    boiled, lag_one = _pixel_series(params, 400, 6, 30.0, 1.0, 0.0, boil=1.0, seed=5, probe=_lag_covariance([1.0]))
    c = (boiled[:, 1:] * boiled[:, :-1]).mean(axis=(0, 1))
    assert np.abs(c).max() < 4 * 0.022
    assert (boiled**2).mean() == pytest.approx(1.0, abs=0.1)
    assert np.abs(lag_one).max() < 1e-12
    frozen, _ = _pixel_series(params, 400, 6, 30.0, 1.0, 0.0, boil=0.0, seed=5)
    assert (frozen[:, 1:] * frozen[:, :-1]).mean() > 0.6


def test_no_wind_no_boiling_gives_identical_frames():
    """(d) end to end: wind 0 and boiling 0 ⇒ every frame is the same image, bit for bit."""
    sim = Simulator(TurbulenceParams(dr0=3.0, n_zernike=15))
    img = torch.rand(1, 3, 40, 48, generator=torch.Generator().manual_seed(0))
    frames = list(sim.sequence(img, frames=4, wind=0.0, generator=torch.Generator().manual_seed(2)))
    for f in frames[1:]:
        assert torch.equal(f.turb, frames[0].turb) and torch.equal(f.fwd_flow_px, frames[0].fwd_flow_px)
    moving = list(sim.sequence(img, frames=2, wind=2.0, generator=torch.Generator().manual_seed(2)))
    assert not torch.equal(moving[0].fwd_flow_px, moving[1].fwd_flow_px)


# ---------------------------------------------------------------------------------------------- API
def test_sequence_frames_are_simulator_frames_with_the_sequence_fields():
    """Each frame is the single-frame simulator run on the state's fields: flow = a_tilt · 2λ/(πD)/ifov;
    deterministic for a seed; a moving input (list of frames) and per-frame depth are used frame by frame."""
    sim = Simulator(TurbulenceParams(dr0=2.5, n_zernike=15))
    img = torch.rand(2, 3, 24, 32, generator=torch.Generator().manual_seed(0))
    run = list(sim.sequence(img, frames=3, fps=25.0, wind=3.0, wind_dir=45, generator=torch.Generator().manual_seed(4)))
    again = list(
        sim.sequence(img, frames=3, fps=25.0, wind=3.0, wind_dir=45, generator=torch.Generator().manual_seed(4))
    )
    assert len(run) == 3 and all(torch.equal(a.turb, b.turb) for a, b in zip(run, again))
    state = FrozenFlow(sim, 2, 24, 32, 25.0, 3.0, 45, 0.0, torch.Generator().manual_seed(4))
    dr0 = torch.full((2,), 2.5, dtype=torch.float64)
    for f in run:
        expected = sim.tilt_fields(2, 24, 32, dr0, unit=state.tilt(2, 24, 32)) * sim.px_per_a2
        assert torch.allclose(f.fwd_flow_px, expected.float(), atol=1e-5)
        state.advance()
    frames = [torch.full((3, 24, 32), v) for v in (0.2, 0.5, 0.8)]
    depth = [torch.full((1, 24, 32), v) for v in (0.0, 0.5, 1.0)]
    out = list(sim.sequence(frames, wind=1.0, depth=depth, generator=torch.Generator().manual_seed(1)))
    assert len(out) == 3
    for f, v, m in zip(out, (0.2, 0.5, 0.8), (0.5**0.6, 0.75**0.6, 1.0)):
        assert torch.allclose(f.clean, torch.full_like(f.clean, v)) and torch.allclose(f.turb, f.clean, atol=1e-5)
        assert f.modulation.mean().item() == pytest.approx(m, rel=1e-5)


def test_sequence_bad_arguments():
    sim = Simulator(TurbulenceParams())
    img = torch.rand(1, 3, 16, 16)
    for kwargs, msg in [
        (dict(frames=0), "frames"),
        (dict(frames=2, fps=0), "fps"),
        (dict(frames=2, boil=1.5), "boil"),
        (dict(frames=2, wind=-1.0), "wind"),
        (dict(frames=2, wind=[1.0, float("nan")]), "wind"),
        (dict(), "frames is required"),
    ]:
        with pytest.raises(D2TurbError, match=msg):
            sim.sequence(img, **kwargs)
    with pytest.raises(D2TurbError, match="does not match"):
        list(sim.sequence([torch.rand(3, 16, 16), torch.rand(3, 16, 20)], wind=1.0))


def test_plane_wave_grid_matches_direct_sums():
    """The non-uniform FFT against the direct sum Σ a e^{2πi f·x} (frequencies beyond ±½ alias like
    point sampling): relative error < 1e-3 at half-width 4 (Greengard & Lee's bound ≈ 1e-4)."""
    gen = torch.Generator().manual_seed(0)
    for h, w in [(37, 50), (64, 64), (3, 5)]:
        grid = PlaneWaveGrid(h, w, half_width=4)
        f = (torch.rand(2, 300, 2, generator=gen, dtype=torch.float64) - 0.5) * 3
        a = torch.randn(2, 300, 2, generator=gen, dtype=torch.float64)
        a = torch.complex(a[..., 0], a[..., 1])
        out = grid(grid.plan(f), a)
        y, x = torch.meshgrid(torch.arange(h).double(), torch.arange(w).double(), indexing="ij")
        phase = 2 * math.pi * (f[..., 0, None, None] * y + f[..., 1, None, None] * x)
        direct = (a[..., None, None] * torch.polar(torch.ones_like(phase), phase)).sum(1)
        assert ((out - direct).abs().max() / direct.abs().max()).item() < 1e-3


def test_state_memory_does_not_grow():
    """Constant memory: the state holds the same tensors after 1 and after 100 frames."""
    state = FrozenFlow(Simulator(TurbulenceParams()), 1, 8, 8, boil=0.1, generator=torch.Generator().manual_seed(0))

    def size():
        return sum(v.numel() * v.element_size() for v in vars(state).values() if isinstance(v, torch.Tensor))

    before = size()
    for _ in range(100):
        state.tilt(1, 8, 8)
        state.high(2, 2, (7.0, 7.0))
        state.advance()
    assert size() == before and state.frame == 100


# ---------------------------------------------------------------------------------------------- CLI
@pytest.fixture(scope="module")
def still(tmp_path_factory):
    from PIL import Image
    from skimage import data

    path = tmp_path_factory.mktemp("still") / "astro.png"
    Image.fromarray(data.astronaut()[::8, ::8][:40, :50]).save(path)  # 50×40
    return path


def test_simulate_video_cli(still, tmp_path, capsys):
    """PNG per frame, tilt and flow on request, meta.json, and a playable mp4 (decoded again with pyav);
    flow f is the forward displacement of frame f: warp(clean, flow_f) = tilt_f (8-bit rounding)."""
    pytest.importorskip("av")
    iio = pytest.importorskip("imageio.v3")
    from d2turb.cli import main
    from d2turb.io import read_image
    from d2turb.ops import warp

    out = tmp_path / "clip"
    args = ["simulate-video", str(still), "--out", str(out), "--frames", "5", "--fps", "25", "--wind", "1", "3"]
    assert main([*args, "--wind-dir", "60", "--save-flow", "--save-tilt", "--depth", "prior", "--seed", "3"]) == 0
    assert sorted(p.name for p in (out / "turb").iterdir()) == [f"{i:06d}.png" for i in range(5)]
    meta = __import__("json").loads((out / "meta.json").read_text())
    assert meta["frames"] == 5 and meta["wind_m_s"] == [1.0, 3.0] and meta["mp4"] == "turb.mp4"
    assert len(meta["layers"]) == 12 and meta["layers"][0]["wind_m_s"] < meta["layers"][-1]["wind_m_s"]
    video = iio.imread(out / "turb.mp4", plugin="pyav")
    assert video.shape == (5, 40, 50, 3)
    first = read_image(out / "turb" / "000000.png").permute(1, 2, 0).numpy() * 255
    assert np.abs(video[0].astype(float) - first).mean() < 8  # lossy H.264 of the same frame
    clean = read_image(still)[None]
    for i in (0, 4):
        flow = torch.from_numpy(np.load(out / "fwd_flow_px" / f"{i:06d}.npy"))[None]
        tilt = read_image(out / "tilt" / f"{i:06d}.png")[None]
        assert (warp(clean, flow) - tilt).abs().max() < 1 / 255 + 1e-4
    # a moving input, frame by frame (the clip just written), and bad input
    again = tmp_path / "again"
    assert main(["simulate-video", str(out / "turb.mp4"), "--out", str(again), "--frames", "3", "--no-mp4"]) == 0
    assert len(list((again / "turb").iterdir())) == 3 and not (again / "turb.mp4").exists()
    capsys.readouterr()
    for bad, msg in [(["--boil", "2"], "boil must be in [0, 1]"), (["--wind", "-1"], "wind speeds must be")]:
        assert main(["simulate-video", str(still), "--out", str(tmp_path / "bad"), *bad]) == 2
        assert msg in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def _make_args(clean, out, frames=8, pairs=8):
    return [
        *("make-dataset", "--clean", str(clean), "--out", str(out), "--pairs", str(pairs), "--patch", "32"),
        *("--batch", "2", "--seed", "5", "--depth", "prior", "--device", "cpu", "--no-progress"),
        *("--frames", str(frames), "--fps", "30", "--wind", "2", "--boil", "0.05"),
    ]


@pytest.mark.slow
def test_make_dataset_frames_restarts_byte_identically(still, tmp_path):
    """make-dataset --frames 8: filmstrip samples pass check-dataset and load as sequences; killed with
    SIGKILL part-way through writing a sample and rerun, the dataset is byte-identical to an uninterrupted run."""
    import signal

    from hostile_input import CHILD_ENV, run_killed_at_rename

    from d2turb.cli import main
    from d2turb.data import PairDataset, SequenceDataset, check_dataset

    clean = still.parent
    ref = tmp_path / "ref"
    assert main(_make_args(clean, ref)) == 0
    assert check_dataset(ref).ok
    ds = SequenceDataset(ref)
    item = ds[0]
    assert (
        item["turb"].shape == (8, 3, 32, 32)
        and item["bwd_flow_px"].shape == (8, 2, 32, 32)
        and item["gt"].shape == (3, 32, 32)
    )
    assert not torch.equal(item["turb"][0], item["turb"][1])
    from d2turb.ops import warp

    inner = (slice(None), slice(None), slice(4, -4), slice(4, -4))
    gt = item["gt"].expand_as(item["tilt"])
    undone = (warp(item["tilt"], item["bwd_flow_px"]) - gt)[inner].abs().mean()
    assert undone < 0.8 * (item["tilt"] - gt)[inner].abs().mean()  # the flow of every frame undoes its tilt
    assert SequenceDataset(ref, frames=2)[1]["tilt"].shape == (2, 3, 32, 32)
    with pytest.raises(D2TurbError, match="SequenceDataset"):
        PairDataset(ref)

    # killed at its 19th file rename: dataset.json, the 10 files of chunk 0 (samples 0, 1) and 7 of chunk 1's
    # 10, so the kill falls inside chunk 1, with one file written under its temporary name; on 2 threads, unlike
    # this process under xdist (a resume on another thread count gives the same bytes)
    out = tmp_path / "killed"
    proc = run_killed_at_rename(19, _make_args(clean, out), env={**CHILD_ENV, "OMP_NUM_THREADS": "2"})
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert 2 <= (out / ".meta" / "rank-0.jsonl").read_bytes().count(b"\n") < 4
    assert any(".tmp" in p.name for p in out.rglob("*"))  # the killed write's temporary file
    assert not check_dataset(out).ok
    assert main(_make_args(clean, out)) == 0  # the rerun resumes from what is on disk: in this process
    assert check_dataset(out).ok
    files = sorted(p.relative_to(ref) for p in ref.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file())
    assert all((ref / f).read_bytes() == (out / f).read_bytes() for f in files)
