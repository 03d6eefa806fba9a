"""Clip restoration (d2turb.clip, d2turb.clip.registration, d2turb.sim.otf) against known synthetic truths:
frames that are known warps of one image, a pure translation, a moving square, identical frames; the OTF against
Fried's formula by hand; the command's bad inputs."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import torch
from scipy import ndimage
from skimage import data as skdata

from d2turb.clip import FUSIONS, ClipRestorer, PhysicsDeblur, wiener_padding, window_start
from d2turb.clip.blind import BlindDeblur
from d2turb.clip.fba import fourier_burst_accumulation
from d2turb.clip.registration import DenseFlow, global_shift_px, remap, to_gray_u8, to_hwc
from d2turb.errors import D2TurbError
from d2turb.sim.otf import diffraction_otf, turbulence_otf


def _scene(size=128) -> np.ndarray:
    img = skdata.astronaut()[100 : 100 + size, 150 : 150 + size].astype(np.float32) / 255.0
    return np.ascontiguousarray(img)


def _smooth_field(rng, size, sigma_px, amplitude_px) -> np.ndarray:
    f = np.stack([ndimage.gaussian_filter(rng.standard_normal((size, size)), sigma_px) for _ in range(2)], -1)
    return (f / f.std() * amplitude_px).astype(np.float32)


def _scipy_warp(img: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """img(x + flow(x)) with scipy's cubic spline interpolation (an implementation independent of OpenCV)."""
    h, w = flow.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    coords = [yy + flow[..., 1], xx + flow[..., 0]]
    return np.stack([ndimage.map_coordinates(img[..., c], coords, order=3, mode="nearest") for c in range(3)], -1)


def test_otf_against_hand_computed_values():
    # T(0.5) = (2/π)(arccos 0.5 − 0.5·√0.75) = (2/π)(π/3 − √3/4)
    assert float(diffraction_otf(torch.tensor(0.5))) == pytest.approx((2 / math.pi) * (math.pi / 3 - 3**0.5 / 4))
    assert float(diffraction_otf(torch.tensor(0.0))) == pytest.approx(1.0)
    assert float(diffraction_otf(torch.tensor(1.2))) == 0.0
    # long exposure at u = 0.25, D/r0 = 2: exp(−3.44·0.5^(5/3))·T(0.25); tilt removed: × exp(+3.44·0.5^(5/3)·0.25^(1/3))
    u, dr0 = torch.tensor(0.25, dtype=torch.float64), 2.0
    t = (2 / math.pi) * (math.acos(0.25) - 0.25 * math.sqrt(1 - 0.0625))
    assert float(turbulence_otf(u, dr0, alpha=0)) == pytest.approx(t * math.exp(-3.44 * 0.5 ** (5 / 3)), rel=1e-9)
    short = t * math.exp(-3.44 * 0.5 ** (5 / 3) * (1 - 0.25 ** (1 / 3)))
    assert float(turbulence_otf(u, dr0, alpha=1)) == pytest.approx(short, rel=1e-9)


def test_pure_translation_is_recovered_exactly():
    img = _scene(128)
    gray = to_gray_u8(img)
    for dx, dy in [(3, -2), (-5, 4), (0, 7)]:
        moved = np.roll(gray, shift=(-dy, -dx), axis=(0, 1))  # moved(x) = img(x + (dx, dy))
        sx, sy = global_shift_px(gray, moved)
        # moved(x − d) = img(x): the shift mapping the frame onto the reference is −d (phase correlation's
        # sub-pixel peak fit is good to a few hundredths of a pixel on a natural image)
        assert abs(sx + dx) < 0.05 and abs(sy + dy) < 0.05
        flow = np.zeros((*gray.shape, 2), np.float32)
        flow[..., 0], flow[..., 1] = sx, sy
        back = remap(to_hwc(moved[..., None].astype(np.float32) / 255), flow)[..., 0]
        inner = (slice(10, -10), slice(10, -10))
        assert np.abs(back[inner] - gray[inner] / 255).mean() < 2e-3


def test_known_warps_of_one_image_are_recovered():
    """Frames = img(x + Δ_i(x)) with smooth random Δ_i (2 px rms): DIS recovers the backward flow onto img."""
    rng = np.random.default_rng(0)
    img = _scene(128)
    flow = DenseFlow("medium")
    errs, zero = [], []
    for _ in range(4):
        delta = _smooth_field(rng, 128, 10, 2.0)
        frame = _scipy_warp(img, delta)
        est = flow(to_gray_u8(img), to_gray_u8(frame))  # frame(x + est(x)) ≈ img(x)
        # truth: the inverse of Δ, est(x) = −Δ(x + est(x)) ≈ −Δ(x − Δ(x)) to second order
        h, w = delta.shape[:2]
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        inv = -np.stack(
            [ndimage.map_coordinates(delta[..., c], [yy - delta[..., 1], xx - delta[..., 0]], order=1) for c in (0, 1)],
            -1,
        )
        inner = (slice(12, -12), slice(12, -12))
        errs.append(np.linalg.norm(est - inv, axis=-1)[inner].mean())
        zero.append(np.linalg.norm(inv, axis=-1)[inner].mean())
    assert np.mean(errs) < 0.25 * np.mean(zero), (errs, zero)


@pytest.mark.parametrize("fusion", FUSIONS)
def test_identical_frames_come_back_unchanged(fusion):
    img = torch.from_numpy(_scene(96)).permute(2, 0, 1).contiguous()
    outs = list(ClipRestorer(temporal=4, fusion=fusion).restore([img] * 6))
    assert [o.index for o in outs] == list(range(6))
    for o in outs:
        assert torch.abs(o.restored - img).max() < 2e-3
        assert torch.abs(o.bwd_flow_px).max() < 0.05


def test_registered_fusion_beats_the_single_frame_and_the_plain_mean():
    """A static scene under zero-mean random warps: the fused frame is closer to the scene than a frame or the
    unregistered temporal mean."""
    rng = np.random.default_rng(1)
    img = _scene(128)
    deltas = [_smooth_field(rng, 128, 8, 1.5) for _ in range(12)]
    mean_delta = np.mean(deltas, axis=0)
    frames = [torch.from_numpy(_scipy_warp(img, d - mean_delta)).permute(2, 0, 1).contiguous() for d in deltas]
    outs = list(ClipRestorer(temporal=12).restore(frames))
    truth = torch.from_numpy(img).permute(2, 0, 1)
    inner = (slice(None), slice(12, -12), slice(12, -12))

    def mse(x):
        return float(((x - truth)[inner] ** 2).mean())

    fused = np.mean([mse(o.fused) for o in outs])
    single = np.mean([mse(f) for f in frames])
    plain = mse(torch.stack(frames).mean(0))
    assert fused < 0.5 * single and fused < 0.75 * plain, (fused, single, plain)


def test_fba_with_power_zero_is_the_plain_mean_and_keeps_identical_frames():
    """Fourier burst accumulation: p = 0 gives numpy's mean of the frames (the sin² windows of a half overlap sum to
    one); frames that are all the same image come back as that image at any p; odd sizes are covered."""
    rng = np.random.default_rng(3)
    stack = [rng.random((53, 70, 3)).astype(np.float32) for _ in range(5)]
    np.testing.assert_allclose(fourier_burst_accumulation(stack, power=0.0, tile=16), np.mean(stack, 0), atol=1e-5)
    img = _scene(80)
    np.testing.assert_allclose(fourier_burst_accumulation([img] * 4, power=8.0), img, atol=1e-5)


def test_fba_takes_each_frequency_from_the_sharpest_frames():
    """A burst of one scene blurred by a different Gaussian per frame (σ 0.5–2.5 px): FBA is closer to the sharp
    scene than the mean of the frames (Delbracio & Sapiro 2015), and closer the larger p."""
    img = _scene(128)
    sigmas = [0.5, 1.5, 2.5, 2.0, 1.0, 2.5]
    stack = [np.stack([ndimage.gaussian_filter(img[..., c], s) for c in range(3)], -1) for s in sigmas]
    inner = (slice(16, -16), slice(16, -16))

    def mse(x):
        return float(((x - img)[inner] ** 2).mean())

    mean, p4, p11 = (
        mse(np.mean(stack, 0)),
        mse(fourier_burst_accumulation(stack, 4.0)),
        mse(fourier_burst_accumulation(stack, 11.0)),
    )
    assert p11 < p4 < 0.8 * mean, (mean, p4, p11)


def test_fba_bad_arguments_are_one_line_errors():
    frame = np.zeros((16, 16, 3), np.float32)
    for kwargs, message in [({"power": -1.0}, "power"), ({"tile": 7}, "tile"), ({"tile": 4}, "tile")]:
        with pytest.raises(D2TurbError, match=message):
            fourier_burst_accumulation([frame], **kwargs)
    with pytest.raises(D2TurbError, match="at least one frame"):
        fourier_burst_accumulation([])


@pytest.mark.parametrize(
    "fusion, blind, stabilise",
    [("mean", False, True), ("sharpest", False, True), ("mean", True, True), ("mean", False, False)],
)
def test_moving_square_falls_back_to_the_frame_without_ghosts(fusion, blind, stabilise):
    img = _scene(128)
    frames, boxes = [], []
    for i in range(8):
        f = img.copy()
        x0 = 10 + 12 * i
        f[50:70, x0 : x0 + 20] = [1.0, 0.0, 0.0]
        frames.append(torch.from_numpy(f).permute(2, 0, 1).contiguous())
        boxes.append(x0)
    deblur = BlindDeblur() if blind else "none"  # blind: the default deblur of restore --temporal
    outs = list(ClipRestorer(temporal=8, fusion=fusion, deblur=deblur, stabilise=stabilise).restore(frames))
    plain = torch.stack(frames).mean(0)
    for o in outs:
        x0 = boxes[o.index]
        square = o.restored[:, 52:68, x0 + 2 : x0 + 18]
        assert torch.allclose(square.mean((1, 2)), torch.tensor([1.0, 0.0, 0.0]), atol=0.05)  # the object is there
        # where the square is at other times (and not now), the output shows the background, not a ghost
        others = [b for b in boxes if abs(b - x0) >= 24]
        ghost = max(
            float((o.restored - torch.from_numpy(img).permute(2, 0, 1))[:, 52:68, b + 2 : b + 18].abs().mean())
            for b in others
        )
        plain_ghost = max(
            float((plain - torch.from_numpy(img).permute(2, 0, 1))[:, 52:68, b + 2 : b + 18].abs().mean())
            for b in others
        )
        assert ghost < 0.25 * plain_ghost, (ghost, plain_ghost)
        if blind:  # the deblurred output shows the background there, not a sharpened ghost
            assert ghost < 0.05


def test_wiener_undoes_a_known_turbulence_blur():
    """Blur by the short-exposure OTF (applied by FFT on a mirror-padded copy), deconvolve with the same OTF."""
    img = torch.from_numpy(_scene(128)).permute(2, 0, 1).double()
    deb = PhysicsDeblur(dr0=2.0, lambda_over_d_px=2.0, balance=1e-4)
    top, bottom, left, right = wiener_padding(128, 128)
    padded = torch.nn.functional.pad(img[None], (left, right, top, bottom), mode="reflect")[0]
    otf = deb.otf(128, 128)
    blurred = torch.fft.irfft2(torch.fft.rfft2(padded) * otf, s=padded.shape[-2:])
    blurred = blurred[:, top : top + 128, left : left + 128].float()
    restored = deb(blurred)
    err_blur = float(((blurred - img.float()) ** 2).mean())
    err_rest = float(((restored - img.float()) ** 2).mean())
    assert err_rest < 0.5 * err_blur, (err_rest, err_blur)


def test_window_start_and_bounded_memory_on_a_long_stream():
    assert [window_start(i, 4, 10) for i in (0, 1, 2, 5, 8, 9)] == [0, 0, 0, 3, 6, 6]
    assert window_start(3, 8, 5) == 0  # clip shorter than the window
    rng = np.random.default_rng(2)
    base = _scene(32)
    restorer = ClipRestorer(temporal=6, passes=2)
    sizes = []
    frames = (
        torch.from_numpy(np.clip(base + 0.01 * rng.standard_normal(base.shape), 0, 1).astype(np.float32)).permute(
            2, 0, 1
        )
        for _ in range(120)
    )
    count = 0
    for _ in restorer.restore(frames):
        sizes.append(restorer.state.buffered)
        count += 1
    assert count == 120
    # frame images held (raw + one per round): about 3.5 windows' worth, bounded by the window, not the clip's length
    assert max(sizes) <= 4 * 6


def test_clip_errors_are_one_line(tmp_path, capsys):
    from d2turb.io import write_image

    img = torch.from_numpy(_scene(64)).permute(2, 0, 1)
    one = tmp_path / "one"
    write_image(one / "a.png", img)
    mixed = tmp_path / "mixed"
    write_image(mixed / "a.png", img)
    write_image(mixed / "b.png", img[:, :32])
    good = tmp_path / "good"
    for i in range(4):
        write_image(good / f"f{i}.png", img)
    (good / "f9.png").write_bytes(b"not a png")
    tiny = tmp_path / "tiny"  # OpenCV's DIS raises under 12 px and crashed by SIGSEGV at 11x40: refused before it
    for i in range(3):
        write_image(tiny / f"f{i}.png", img[:, :11, :40])

    def run(*args):  # in this process (`main` is what `python -m d2turb` runs): no torch import per case
        from d2turb.cli import main

        rc = main(["restore", *map(str, args)])
        return subprocess.CompletedProcess(args, rc, *capsys.readouterr())

    for args, needle in [
        ((one, "--temporal", 4, "--out", tmp_path / "o1"), "at least 2 frames"),
        ((mixed, "--temporal", 4, "--out", tmp_path / "o2"), "one size"),
        ((good, "--temporal", 1, "--out", tmp_path / "o3"), "--temporal must be an integer >= 2"),
        ((good, "--temporal", 4, "--deblur", "physics", "--out", tmp_path / "o4"), "give --dr0"),
        ((good, "--temporal", 4, "--dr0", -1, "--out", tmp_path / "o5"), "dr0"),
        ((good, "--temporal", 4, "--out", good), "folder of the input files"),
        ((tiny, "--temporal", 3, "--out", tmp_path / "o7"), "too small to register"),
    ]:
        r = run(*args)
        assert r.returncode == 2, (args, r.stderr)
        lines = [line for line in r.stderr.splitlines() if line.startswith("error:")]
        assert len(lines) == 1 and needle in lines[0], r.stderr
        assert "Traceback" not in r.stderr
        if args[-1] != good:  # nothing left behind: no (empty) output folder
            assert not args[-1].exists(), args
    # mixed sizes: the mismatch is said once (not also in notes), before anything is measured or written
    r = run(mixed, "--temporal", 4, "--out", tmp_path / "o2")
    assert r.stderr.count("one size") == 1 and "b.png is 64x32" in r.stderr, r.stderr
    r = run(good, "--temporal", 3, "--out", tmp_path / "o6", "--save-flow")
    assert r.returncode == 1 and "f9.png" in r.stderr and "Traceback" not in r.stderr
    written = sorted(p.name for p in (tmp_path / "o6").glob("*_restored.png"))
    assert written == [f"f{i}_restored.png" for i in range(4)]
    flows = sorted((tmp_path / "o6" / "fwd_flow_px").glob("*.npy"))
    assert len(flows) == 4 and np.load(flows[0]).shape == (2, 64, 64) and np.load(flows[0]).dtype == np.float32


@pytest.mark.slow
def test_clip_video_in_video_out(tmp_path):
    pytest.importorskip("av")
    from d2turb.video import Mp4Writer

    img = torch.from_numpy(_scene(64)).permute(2, 0, 1)
    with Mp4Writer(tmp_path / "clip.mp4", fps=12) as w:
        for _ in range(5):
            w.write(img)
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "d2turb",
            "restore",
            str(tmp_path / "clip.mp4"),
            "--temporal",
            "3",
            "--out",
            str(tmp_path / "out"),
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    import av

    with av.open(str(tmp_path / "out" / "clip_restored.mp4")) as c:
        stream = c.streams.video[0]
        frames = sum(1 for _ in c.decode(stream))
        assert frames == 5 and float(stream.average_rate) == pytest.approx(12, rel=1e-3)
    assert len(list((tmp_path / "out").glob("clip_*_restored.png"))) == 5


def test_evaluate_clips_averages_frames_then_clips_per_bin(tmp_path, monkeypatch):
    """evaluate --clips with the dataset and the clip restorer replaced by known frames: each clip's numbers are
    numpy means over its frames (image metrics on every stride-th frame), each bin's over its clips."""
    import d2turb.eval.clips as clips
    from d2turb.eval.metrics import ssim

    g = torch.Generator().manual_seed(0)
    frames_n, size, stride = 5, 24, 2
    bins = ["weak", "strong", "weak"]
    items = []
    for k in range(len(bins)):
        gt = torch.rand(3, size, size, generator=g)
        turb = (gt + 0.1 * (k + 1) * torch.randn(frames_n, 3, size, size, generator=g)).clamp(0, 1)
        items.append(
            {"id": f"{k:07d}", "turb": turb, "gt": gt, "bwd_flow_px": torch.randn(frames_n, 2, size, size, generator=g)}
        )
    records = [{"bin": b, "dr0": 1.0 + k} for k, b in enumerate(bins)]
    data = type("Data", (), {"records": records, "__len__": lambda s: len(items), "__getitem__": lambda s, i: items[i]})

    class Restorer:  # frame i: fused = (frame + gt) / 2, displacement = observable flow + (0.1 i, 0) px
        def __init__(self, **kwargs):
            pass

        def restore(self, frames):
            item = next(it for it in items if it["turb"] is frames)
            observable = item["bwd_flow_px"] - item["bwd_flow_px"].mean(0, keepdim=True)
            for i in range(len(frames)):
                flow = observable[i] + torch.tensor([0.1 * i, 0.0]).view(2, 1, 1)
                yield type("Out", (), {"index": i, "fused": (frames[i] + item["gt"]) / 2, "bwd_flow_px": flow})

    monkeypatch.setattr(clips, "SequenceDataset", lambda root: data())
    monkeypatch.setattr(clips, "ClipRestorer", Restorer)
    res = clips.evaluate_clips(tmp_path, tmp_path / "out", deblur=["none"], stride=stride, progress=False)

    def psnr_np(a, b):
        return 10 * np.log10(1.0 / ((a.double().numpy() - b.double().numpy()) ** 2).mean())

    expected = []
    for item in items:
        obs = (item["bwd_flow_px"] - item["bwd_flow_px"].mean(0, keepdim=True)).double().numpy()
        turb, gt = item["turb"], item["gt"]
        rows = {"input": list(turb[::stride]), "temporal mean": [turb.mean(0)] * len(turb[::stride])}
        rows["fused"] = [(f + gt) / 2 for f in turb[::stride]]
        sample = {"epe": np.mean([0.1 * i for i in range(frames_n)])}
        sample["epe_zero"] = np.mean([np.sqrt((o**2).sum(0)).mean() for o in obs])
        for row, images in rows.items():
            sample[f"{row} psnr"] = np.mean([psnr_np(im.clamp(0, 1), gt) for im in images])
            sample[f"{row} ssim"] = np.mean([float(ssim(im.clamp(0, 1)[None], gt[None])) for im in images])
        expected.append(sample)
    for got, want in zip(res["samples"], expected):
        assert {k: got[k] for k in want} == pytest.approx(want, rel=1e-6)
    for b in ("weak", "strong"):
        members = [s for s, r in zip(expected, records) if r["bin"] == b]
        want = {k: np.mean([m[k] for m in members]) for k in expected[0]}
        want["dr0"] = np.mean([r["dr0"] for r in records if r["bin"] == b])
        got = {k: res["bins"][b][k] for k in list(want) + ["clips"]}
        assert got == pytest.approx(want | {"clips": len(members)}, rel=1e-6)
        assert {f"{row} psnr_aligned" for row in rows} <= set(res["bins"][b])
        assert {f"{row} cwssim" for row in rows} <= set(res["bins"][b])
    assert list(res["bins"]) == ["weak", "strong"]  # bins in their order, only those with clips


def test_global_offset_removal_recovers_a_known_subpixel_shift():
    """A scene shifted by a known sub-pixel offset (scipy's spline shift, then a smooth low-pass): the estimated
    offset is the shift to 0.05 px, and the offset-removed PSNR is far above the plain one (which punishes the
    offset) while an unshifted copy scores the same both ways."""
    from d2turb.eval.clips import remove_global_offset
    from d2turb.eval.metrics import psnr

    img = ndimage.gaussian_filter(_scene(96), (1.0, 1.0, 0))
    truth = torch.from_numpy(img).permute(2, 0, 1).contiguous()
    for dy, dx in [(1.3, -0.7), (-2.25, 0.4)]:
        moved = np.stack([ndimage.shift(img[..., c], (dy, dx), order=3, mode="nearest") for c in range(3)], 0)
        moved = torch.from_numpy(moved).float()
        back, ref, (ey, ex) = remove_global_offset(moved, truth)
        assert ey == pytest.approx(-dy, abs=0.05) and ex == pytest.approx(-dx, abs=0.05)
        assert float(psnr(back[None], ref[None])) > float(psnr(moved[None], truth[None])) + 10
    same, ref, shift = remove_global_offset(truth, truth)
    assert max(map(abs, shift)) < 1e-6 and torch.allclose(same, ref, atol=1e-5)


def test_residual_jitter_otf_is_the_gaussian_of_the_shifts():
    """The mean of many copies of an image shifted by Gaussian random sub-pixel shifts (σ per axis; scipy's spline
    shift, independent of the FFT) is that image blurred by the Gaussian; the jitter OTF of PhysicsDeblur, with the
    turbulence switched off (modulation → 0), deconvolves it: much closer to the image than the jittered mean, and
    closer than the same filter without the jitter term."""
    rng = np.random.default_rng(5)
    img = _scene(96)[..., 1].astype(np.float64)
    sigma = 1.2
    shifts = rng.normal(0, sigma, (400, 2))
    mean = np.mean([ndimage.shift(img, s, order=3, mode="reflect") for s in shifts], axis=0)
    t = torch.from_numpy(np.stack([mean] * 3)).float()
    truth = torch.from_numpy(np.stack([img] * 3)).float()
    kw = {"modulation": 1e-9, "balance": 1e-5, "prior": "laplacian"}  # a weak prior: the noise-free mean
    sharp = PhysicsDeblur(1.0, jitter_px=sigma, **kw)(t)
    plain = PhysicsDeblur(1.0, **kw)(t)

    def err(x):
        return float(((x - truth)[:, 8:-8, 8:-8] ** 2).mean())

    assert err(sharp) < 0.3 * err(t), (err(sharp), err(t))
    assert err(sharp) < 0.5 * err(plain), (err(sharp), err(plain))
    with pytest.raises(D2TurbError, match="jitter"):
        PhysicsDeblur(1.0, jitter_px=-1.0)


def test_registration_tilt_variance_scales_with_the_known_warps():
    """Frames that are independent known smooth warps of one image (scipy's spline warp): the registered flows'
    per-axis variance (each frame's mean removed) grows like the square of the warps' amplitude (×2 → ×4, within
    25 %) and stays below the warps' own variance about their mean over the window (the fusion's geometry): the
    registration onto a fusion sees only part of it (what OBSERVED_TILT_SHARE calibrates on the simulated clips)."""
    from d2turb.clip import registration_tilt_variance

    img = _scene(128)
    got, truth = [], []
    for amplitude in (1.0, 2.0):
        rng = np.random.default_rng(11)  # the same fields, scaled
        fields = [_smooth_field(rng, 128, 10.0, amplitude) for _ in range(16)]
        frames = [_scipy_warp(img, f).astype(np.float32) for f in fields]
        centred = np.stack(fields) - np.mean(fields, axis=0)
        truth.append(float(np.mean([((c - c.mean((0, 1))) ** 2).mean() for c in centred])))
        got.append(registration_tilt_variance(frames, temporal=16, preset="medium"))
    assert 3.0 < got[1] / got[0] < 5.0, got
    assert got[0] < truth[0] and got[1] < truth[1], (got, truth)


def test_8bit_frames_as_stored_restore_exactly_as_their_float_reading(tmp_path):
    """An 8-bit clip given as (H,W,3) uint8 arrays (d2turb.io.read_frame, what `restore --temporal` reads) restores
    bit for bit as the same frames read as k/255 float tensors (d2turb.io.read_image): one pipeline, two readings."""
    from d2turb.io import read_frame, read_image, write_image

    rng = np.random.default_rng(3)
    scene = _scene(64)
    paths = []
    for i in range(6):
        shifted = np.roll(scene, (i % 3) - 1, axis=1) + 0.02 * rng.standard_normal(scene.shape)
        paths.append(tmp_path / f"f{i}.png")
        write_image(paths[-1], torch.from_numpy(np.clip(shifted, 0, 1).astype(np.float32)).permute(2, 0, 1))
    stored = [read_frame(p) for p in paths]
    assert all(isinstance(f, np.ndarray) and f.dtype == np.uint8 and f.shape == (64, 64, 3) for f in stored)
    a = list(ClipRestorer(temporal=4, deblur=BlindDeblur()).restore(stored))
    b = list(ClipRestorer(temporal=4, deblur=BlindDeblur()).restore(read_image(p) for p in paths))
    for x, y in zip(a, b, strict=True):
        assert torch.equal(x.restored, y.restored) and torch.equal(x.bwd_flow_px, y.bwd_flow_px)
    # a 16-bit frame is not 8-bit: read as read_image gives it
    write_image(tmp_path / "deep.png", (rng.random((8, 8)) * 65535).astype(np.uint16))
    assert isinstance(read_frame(tmp_path / "deep.png"), torch.Tensor)


def test_unit_float_is_the_correctly_rounded_k_over_255():
    """8-bit frames as float32 k/255 through a table (OpenCV's LUT): every level equals IEEE's correctly rounded
    division, in every layout the pipeline holds (grey, one channel, colour, with alpha, not contiguous)."""
    from d2turb.clip.registration import unit_float

    levels = np.arange(256, dtype=np.uint8)
    expected = np.float32(levels.astype(np.float32) / np.float32(255))
    rng = np.random.default_rng(0)
    for shape in [(16, 16), (16, 16, 1), (16, 16, 3), (16, 16, 4), (4, 8, 8)]:
        image = rng.integers(0, 256, shape).astype(np.uint8)
        for im in (image, image[:, ::-1]):
            got = unit_float(im)
            assert got.dtype == np.float32 and got.shape == im.shape
            np.testing.assert_array_equal(got, expected[im])
    for shape in [(0, 5, 3), (5, 0), (0, 0, 1)]:  # empty: the caller's size check speaks, not OpenCV
        assert unit_float(np.zeros(shape, np.uint8)).shape == shape
