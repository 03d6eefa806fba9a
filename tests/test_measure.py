"""Turbulence measurement (d2turb.clip.strength, docs/measure.md): the formula inversion against hand-computed values,
the differential-tilt theory against the tested tilt correlation, a clip shifted by a known random field, camera shake
cancelling for a pure global translation, the interval (quadrature sum by hand, coverage of a known log-normal), the
registration-gain table's interpolation, and bad input through the command line as one ``error:`` line."""

import math

import cv2
import numpy as np
import pytest

from d2turb.cli import main
from d2turb.clip import strength as M
from d2turb.errors import D2TurbError
from d2turb.sim.tilt import (
    differential_tilt_covariance,
    dr0_from_tilt_variance,
    tilt_correlation,
    tilt_variance_px2,
)


def test_tilt_variance_inversion_against_hand_computed_values():
    # Nyquist sampling: λ/(D·ifov) = 2, σ² = 0.1816·4·2.5^(5/3) = 0.7264·4.60503 = 3.34510 px²
    assert tilt_variance_px2(2.5, 2.0) == pytest.approx(3.34510, rel=1e-5)
    assert dr0_from_tilt_variance(3.34510, 2.0) == pytest.approx(2.5, rel=1e-5)
    # ifov twice Nyquist (λ/(D·ifov) = 1): σ² four times smaller for the same D/r0
    assert dr0_from_tilt_variance(3.34510 / 4, 1.0) == pytest.approx(2.5, rel=1e-5)


def test_r0_cn2_theta0_against_the_worked_value():
    # docs/physics.md §3: Cn² = 1e-14, L = 1 km, λ = 0.5 µm → r0 = 3.6368 cm (spherical wave)
    optics = M.Optics(aperture_m=0.1, wavelength_m=0.5e-6, path_length_m=1000.0)
    out = M.r0_cn2_theta0(0.1 / 0.036368, optics)
    assert out["r0_m"] == pytest.approx(0.036368, rel=1e-5)
    assert out["cn2"] == pytest.approx(1e-14, rel=1e-4)
    # θ0 = (2.914 k² Cn² L^(8/3) B(8/3, 8/3))^(−3/5), k = 1.25664e7, B = 0.0564118 → 35.5986 µrad
    assert out["theta0_urad"] == pytest.approx(35.5986, rel=1e-4)
    no_path = M.r0_cn2_theta0(2.0, M.Optics())
    with pytest.raises(D2TurbError, match="unknown optics"):
        M.as_optics({"focal_m": 1.0})
    from d2turb.sim import TurbulenceParams

    assert M.as_optics(TurbulenceParams(path_length_m=500.0)).path_length_m == 500.0
    assert no_path["cn2"] is None and no_path["theta0_urad"] is None and no_path["r0_m"] == pytest.approx(0.05)


def test_differential_tilt_at_zero_lag_is_the_tested_tilt_correlation():
    a = 525e-9 / 0.2 * 1000.0 / 0.1  # ifov·L/D of the default optics
    seps = [8, 32, 128]
    g = differential_tilt_covariance([[r, 0] for r in seps], [0], a, n_layers=48)[:, :, 0]
    perp, par = tilt_correlation(np.array(seps) * 525e-9 / 0.2, 0.1, 1000.0)
    np.testing.assert_allclose(g[:, 0], 2 * (1 - par), rtol=1e-6)  # x component along an x separation: parallel
    np.testing.assert_allclose(g[:, 1], 2 * (1 - perp), rtol=1e-6)
    # boiling: (1 − boil)^(τ/2) decay of every lag; a fast wind decorrelates the differential tilt within a frame
    slow = differential_tilt_covariance([[32, 0]], [0, 4], a, 0.0, boil=0.19)[0, 0]
    assert slow[1] == pytest.approx(slow[0] * 0.81**2, rel=1e-9)
    fast = differential_tilt_covariance([[32, 0]], [0, 1], a, 3.0)[0, 0]
    assert abs(fast[1]) < 0.1 * fast[0]


def _texture(size: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.random((size, size)).astype(np.float32), (0, 0), 1.5)
    return (img - img.min()) / (img.max() - img.min())


def _warp(img: np.ndarray, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    h, w = img.shape
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(img, gx + dx.astype(np.float32), gy + dy.astype(np.float32), cv2.INTER_CUBIC, cv2.BORDER_REFLECT)


def test_known_random_field_gives_its_differential_variance():
    """Frames shifted by d(x, t) = A_t sin(kx) + B_t cos(kx) (x component; A, B independent normals: a homogeneous
    field, like the tilt): the differential displacement at separation r along x has the structure function
    ⟨(u(t+τ) − u(t))²⟩ = mean over t and the pairs of (ΔA (sin kx − sin k(x+r)) + ΔB (cos kx − cos k(x+r)))²."""
    size, period, frames = 96, 48.0, 16
    k = 2 * np.pi / period
    rng = np.random.default_rng(3)
    amp_a, amp_b = rng.normal(0.0, 0.5, frames), rng.normal(0.0, 0.5, frames)
    base = _texture(size + 32, 1)
    x = np.arange(size + 32, dtype=np.float64)[None, :].repeat(size + 32, 0)
    clip = [
        _warp(base, a * np.sin(k * x) + b * np.cos(k * x), np.zeros_like(x))[16:-16, 16:-16]
        for a, b in zip(amp_a, amp_b)
    ]
    flows, mask, diag = M.register_clip((np.stack(clip) * 255).astype(np.float32))
    assert diag["valid_fraction"] > 0.8
    num, pairs, series = M.lag_sums(flows, mask, [12, 24])
    lags = np.arange(1, frames)
    for j, (r, orient, comp) in enumerate(series):
        pooled = num.sum(0)[j, 1:].sum() / (pairs.sum(0)[j] * np.sum(frames - lags))
        ys, xs = np.nonzero(mask[::2, ::2])
        ys, xs = 2 * ys, 2 * xs
        keep = (xs + r < size) & mask[ys, np.minimum(xs + r, size - 1)]
        x0 = xs[keep] + 16.0  # the pairs' first points in the coordinates of the warped field
        ds, dc = np.sin(k * x0) - np.sin(k * (x0 + r)), np.cos(k * x0) - np.cos(k * (x0 + r))
        sq = [((amp_a[t:] - amp_a[:-t])[:, None] * ds + (amp_b[t:] - amp_b[:-t])[:, None] * dc) ** 2 for t in lags]
        expected = sum(q.sum() for q in sq) / (len(x0) * np.sum(frames - lags))
        if (orient, comp) == (0, 0):
            # DIS keeps 85–95 % of the differential power of this 0.5-px, 48-px-period field (its registration gain)
            assert 0.8 * expected < pooled < 1.05 * expected, (r, pooled, expected)
        else:  # no y displacement, and the x displacement does not vary along y: registration noise only
            assert pooled < 0.01, (r, orient, comp, pooled)


def test_lag_sums_is_the_direct_structure_function():
    rng = np.random.default_rng(4)
    flows = rng.normal(0, 1, (9, 30, 34, 2))
    mask = rng.random((30, 34)) > 0.2
    num, pairs, series = M.lag_sums(flows, mask, [3, 7], tiles=2)
    for j, (r, orient, comp) in enumerate(series):
        dy, dx = (0, r) if orient == 0 else (r, 0)
        total, count = np.zeros(9), 0
        for y in range(0, 30, 2):
            for x in range(0, 34, 2):
                if y + dy < 30 and x + dx < 34 and mask[y, x] and mask[y + dy, x + dx]:
                    u = flows[:, y, x, comp] - flows[:, y + dy, x + dx, comp]
                    total += [np.sum((u[t:] - u[: 9 - t]) ** 2) for t in range(9)]
                    count += 1
        np.testing.assert_allclose(num.sum(0)[j], total, rtol=1e-9, atol=1e-9)
        assert pairs.sum(0)[j] == count


def test_camera_shake_cancels_exactly_for_a_global_translation():
    rng = np.random.default_rng(0)
    flows = rng.normal(0, 1, (12, 40, 40, 2)).astype(np.float64)
    shake = rng.uniform(-3, 3, (12, 1, 1, 2))
    mask = np.ones((40, 40), bool)
    a = M.lag_sums(flows, mask, [4, 8])
    b = M.lag_sums(flows + shake, mask, [4, 8])
    np.testing.assert_allclose(a[0], b[0], atol=1e-9)
    np.testing.assert_array_equal(a[1], b[1])


def test_pure_global_translation_measures_no_turbulence():
    base = _texture(160, 2)
    rng = np.random.default_rng(1)
    shifts = rng.integers(-3, 4, (12, 2))
    clip = [np.roll(base, tuple(s), axis=(0, 1))[16:-16, 16:-16] for s in shifts]
    out = M.measure_clip(clip, {"path_length_m": 1000.0, "ifov_rad": 525e-9 / 0.2}, bootstrap=20)
    # no differential motion: D/r0 of ~0 (a registration noise floor of a few hundredths of a pixel)
    assert out["dr0"] < 0.15 and out["dr0_ci"][0] <= out["dr0"] <= out["dr0_ci"][1]
    sds = out["dr0_log_sd"]
    assert sds["clip"] == M.clip_log_sd(out["dr0"], 12)  # clamped below D/r0 = 1.5, widened for 12 frames
    assert sds["clip"] == pytest.approx(math.sqrt(M.CLIP_LOG_SD[0] ** 2 + M.CLIP_WINDOW_VAR * (64 / 12 - 1)))
    np.testing.assert_allclose(out["dr0_ci"], M.log_normal_interval(out["dr0"], (sds["tiles"], sds["clip"])))


def test_footprint_below_the_calibrated_gain_is_widened_not_refused():
    base = _texture(160, 2)
    rng = np.random.default_rng(1)
    clip = [np.roll(base, tuple(s), axis=(0, 1))[16:-16, 16:-16] for s in rng.integers(-3, 4, (12, 2))]
    # D/(ifov·L) = 0.05 / (5e-6 · 5000) = 2.0 px: below the 4 px of the gain table, an extra log-sd of
    # EXTRAPOLATION_LOG_SD·ln(4/2) instead of a refusal (no turbulence here: an upper bound near 0 is the answer)
    optics = {"aperture_m": 0.05, "wavelength_m": 5e-7, "ifov_rad": 5e-6, "path_length_m": 5000.0}
    out = M.measure_clip(clip, optics, bootstrap=5)
    assert out["fit"]["footprint_px"] == pytest.approx(2.0)
    assert out["dr0_ci"][1] < M.NEGLIGIBLE_DR0 and out["parameters"]["given"] == ["ifov_rad", "path_length_m"]


def test_interval_is_the_quadrature_sum_against_hand_computed_values():
    # s = sqrt(0.03² + 0.04²) = 0.05; normal quantile: z·s = 1.6448536·0.05 = 0.0822427, e^0.0822427 = 1.0857195
    lo, hi = M.log_normal_interval(2.0, (0.03, 0.04), z=1.6448536)
    assert lo == pytest.approx(2.0 / 1.0857195, rel=1e-6) and hi == pytest.approx(2.0 * 1.0857195, rel=1e-6)
    # the default quantile, t_0.95 with 154 degrees of freedom = 1.6548084: z·s = 0.0827404, e^0.0827404 = 1.0862598
    lo, hi = M.log_normal_interval(2.0, (0.03, 0.04))
    assert lo == pytest.approx(2.0 / 1.0862598, rel=1e-6) and hi == pytest.approx(2.0 * 1.0862598, rel=1e-6)
    assert M.log_normal_interval(3.0, (0.0, 0.0)) == (3.0, 3.0)


def test_default_quantile_is_the_student_t_95th_percentile():
    # the Student-t density f(t) = Γ((ν+1)/2) / (sqrt(νπ) Γ(ν/2)) (1 + t²/ν)^(−(ν+1)/2), integrated from 0 to Z90 by
    # Simpson's rule, holds 0.45 of the probability (two-sided 90 %); tables: t_0.95(120) = 1.658, t_0.95(200) = 1.653
    nu = M.CLIP_DOF
    c = math.exp(math.lgamma((nu + 1) / 2) - math.lgamma(nu / 2)) / math.sqrt(nu * math.pi)
    t = np.linspace(0.0, M.Z90, 2001)
    f = c * (1 + t**2 / nu) ** (-(nu + 1) / 2)
    h = t[1] - t[0]
    mass = h / 3 * (f[0] + f[-1] + 4 * f[1:-1:2].sum() + 2 * f[2:-1:2].sum())
    assert mass == pytest.approx(0.45, abs=1e-7)
    assert 1.653 < M.Z90 < 1.658


def test_interval_covers_a_known_log_normal_90_percent_of_the_time():
    # an oracle independent of the estimator: ln D̂ = ln D + e_tiles + e_clip, both normal with known sds; the
    # interval from the two sds with the normal quantile covers D in 90 % of draws, the tiles' sd alone (the old
    # interval) in far fewer
    rng = np.random.default_rng(0)
    truth, s_tiles, s_clip, n = 3.0, 0.02, 0.04, 20000
    est = truth * np.exp(rng.normal(0, s_tiles, n) + rng.normal(0, s_clip, n))
    z = 1.6448536269514722
    both = [M.log_normal_interval(e, (s_tiles, s_clip), z=z) for e in est]
    alone = [M.log_normal_interval(e, (s_tiles,), z=z) for e in est]
    cover_both = np.mean([lo <= truth <= hi for lo, hi in both])
    cover_alone = np.mean([lo <= truth <= hi for lo, hi in alone])
    assert abs(cover_both - 0.90) < 0.01  # binomial sd 0.002
    assert abs(cover_alone - (2 * 0.5 * (1 + math.erf(1.6448536 * 0.02 / np.hypot(0.02, 0.04) / 2**0.5)) - 1)) < 0.01


def test_clip_term_interpolates_in_the_strength():
    assert M.clip_log_sd(M.GAIN_DR0[1]) == M.CLIP_LOG_SD[1]
    mid = (M.GAIN_DR0[1] + M.GAIN_DR0[2]) / 2
    assert M.clip_log_sd(mid) == pytest.approx((M.CLIP_LOG_SD[1] + M.CLIP_LOG_SD[2]) / 2, rel=1e-12)
    assert M.clip_log_sd(0.3) == M.CLIP_LOG_SD[0] and M.clip_log_sd(9.0) == M.CLIP_LOG_SD[-1]
    # a window of 32 frames: variance s² + CLIP_WINDOW_VAR·(64/32 − 1); longer clips keep the 64-frame term
    s, c = M.CLIP_LOG_SD[1], M.CLIP_WINDOW_VAR
    assert M.clip_log_sd(M.GAIN_DR0[1], 32) == pytest.approx(math.sqrt(s * s + c), rel=1e-12)
    assert M.clip_log_sd(M.GAIN_DR0[1], 16) == pytest.approx(math.sqrt(s * s + 3 * c), rel=1e-12)
    assert M.clip_log_sd(M.GAIN_DR0[1], 300) == M.clip_log_sd(M.GAIN_DR0[1], 64) == s


def test_registration_gain_interpolates_the_table():
    table = np.asarray(M.GAIN_TABLE)
    for f, row in zip(M.GAIN_FOOTPRINT_PX, table):
        for x, cell in zip(M.GAIN_DR0, row):
            np.testing.assert_allclose(M.registration_gain(M.GAIN_SEPARATIONS_PX, x, f), cell, rtol=1e-12)
    # midway in ln footprint, D/r0 and ln r: the mean of the two neighbours along each axis
    f_mid = float(np.sqrt(M.GAIN_FOOTPRINT_PX[0] * M.GAIN_FOOTPRINT_PX[1]))
    x_mid = (M.GAIN_DR0[0] + M.GAIN_DR0[1]) / 2
    r_mid = float(np.sqrt(M.GAIN_SEPARATIONS_PX[0] * M.GAIN_SEPARATIONS_PX[1]))
    assert M.registration_gain([r_mid], x_mid, f_mid)[0] == pytest.approx(table[:2, :2, :2].mean(), rel=1e-12)
    # clamped outside the calibrated footprints and strengths
    np.testing.assert_allclose(M.registration_gain([16, 64], 9.0, 1000.0), table[-1, -1, [0, -1]], rtol=1e-12)
    np.testing.assert_allclose(M.registration_gain([16, 64], 0.5, 1.0), table[0, 0, [0, -1]], rtol=1e-12)


def _write_frames(folder, frames):
    folder.mkdir()
    for i, f in enumerate(frames):
        cv2.imwrite(str(folder / f"{i:03d}.png"), np.clip(f * 255 + 0.5, 0, 255).astype(np.uint8))
    return folder


@pytest.mark.parametrize(
    "case, message",
    [
        ("one", "at least 8 frames"),
        ("constant", "constant"),
        ("sizes", "frame 3 is"),
        ("flat", "cannot measure this clip"),
        ("aperture", "aperture_m must be positive"),
        ("wavelength", "not smaller than the aperture"),
        ("key", "unknown key"),
        ("missing", "no such file"),
        ("pitch", "--pixel-pitch needs --focal-length"),
        ("focal", "--focal-length needs --pixel-pitch"),
        ("ifov_twice", "ifov_rad given twice"),
        ("f_number", "--f-number must be positive"),
        ("grey", "has texture (need 2 %): a flat scene"),
    ],
)
def test_bad_input_is_one_error_line(tmp_path, capsys, case, message):
    tex = [_texture(64, i) for i in range(10)]
    params = ["--path-length", "1000"]
    if case == "one":
        clip = _write_frames(tmp_path / "c", tex[:1])
    elif case == "constant":
        clip = _write_frames(tmp_path / "c", [np.full((64, 64), 0.5)] * 10)
    elif case == "sizes":
        clip = _write_frames(tmp_path / "c", tex[:3] + [np.zeros((60, 64))] + tex[4:])
    elif case == "grey":  # a constant grey with camera noise: the cause is the texture, not the registration
        rng = np.random.default_rng(7)
        clip = _write_frames(tmp_path / "c", [np.clip(0.6 + rng.normal(0, 1 / 255, (96, 96)), 0, 1) for _ in range(10)])
    elif case == "flat":  # a smooth ramp with a little noise: no texture to register
        ramp = np.linspace(0.3, 0.35, 64)[None, :].repeat(64, 0)
        noisy = [ramp + 0.002 * np.random.default_rng(i).random((64, 64)) for i in range(10)]
        clip = _write_frames(tmp_path / "c", noisy)
    else:
        clip = _write_frames(tmp_path / "c", tex)
        params += {
            "aperture": ["--aperture", "-1"],
            "wavelength": ["--wavelength", "0.2"],
            "key": ["--param", "focal=3"],
            "missing": [],
            "pitch": ["--pixel-pitch", "5e-6"],
            "focal": ["--focal-length", "0.3"],
            "ifov_twice": ["--ifov", "1e-5", "--pixel-pitch", "5e-6", "--focal-length", "1.0"],
            "f_number": ["--focal-length", "0.3", "--f-number", "0"],
        }[case]
        if case == "missing":
            clip = tmp_path / "nothing"
    rc = main(["measure", str(clip), "--out", str(tmp_path / "out"), *params])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("error:") and message in err[0], err


def test_camera_data_sheet_values_give_the_ifov_and_the_aperture():
    # ifov = pixel pitch / focal length, D = focal length / f-number (docs/measure.md, "What you know"): 3.45 µm and
    # 400 mm give 8.625 µrad; 400 mm at f/8 gives 50 mm; λ/(D·ifov) = λ·N/pitch = 525e-9·8/3.45e-6 = 1.2174 px
    from d2turb.cli import build_parser
    from d2turb.commands import measure
    from d2turb.sim import Optics

    args = ["measure", "c", "--out", "o", "--pixel-pitch", "3.45e-6", "--focal-length", "0.4", "--f-number", "8"]
    given = measure.optics_of(build_parser().parse_args(args))
    assert given == {"ifov_rad": pytest.approx(8.625e-6, rel=1e-12), "aperture_m": pytest.approx(0.05, rel=1e-12)}
    assert Optics(**given).lambda_over_d_px == pytest.approx(1.2173913, rel=1e-6)
    same = build_parser().parse_args([*args, "--ifov", "8.625e-6", "--aperture", "0.05"])  # agreeing: accepted
    assert measure.optics_of(same) == given


def test_measure_command_answers_with_its_interval_and_a_note(tmp_path, capsys, monkeypatch):
    base = _texture(112, 5)
    rng = np.random.default_rng(2)
    x = np.arange(112, dtype=np.float64)[None, :].repeat(112, 0)
    y = x.T
    frames = []
    for _ in range(16):  # a smooth random displacement field per frame
        a, b = rng.normal(0, 0.7, 2)
        frames.append(_warp(base, a * np.sin(2 * np.pi * x / 40), b * np.cos(2 * np.pi * y / 40))[8:-8, 8:-8])
    clip = _write_frames(tmp_path / "c", frames)
    out = tmp_path / "out"
    import json

    # nothing given: ρ is the answer, first in the line; D/r0 and r0 need the camera; its interval spans more than
    # 3x: answered all the same (exit 0), with one note line naming what narrows it most
    assert main(["measure", str(clip), "--out", str(tmp_path / "blind"), "--bootstrap", "20"]) == 0
    captured = capsys.readouterr()
    line, notes = captured.out.strip().splitlines(), captured.err.strip().splitlines()
    assert len(line) == 1 and line[0].startswith("c: seeing angle ρ = λ/(r0·ifov) = "), line
    assert "D/r0 and r0 need the camera's ifov" in line[0] and "given: none" in line[0]
    blind = json.loads((tmp_path / "blind" / "measure.json").read_text())
    assert blind["r0_m"] is None and blind["cn2"] is None and list(blind)[0] == "answer"  # ρ first (sorted keys)
    assert blind["answer"] == {
        "quantity": "seeing_px",
        "value": blind["seeing_px"],
        "ci": blind["seeing_px_ci"],
        "unit": "px",
    }
    span = blind["seeing_px_ci"][1] / blind["seeing_px_ci"][0]
    assert blind["narrowing"]["seeing_px"]["span"] == pytest.approx(span)
    assert len(notes) == (span > M.MAX_SPAN), notes  # a note only beyond 3x
    # a note: one line, the span and what narrows it most, to about the span it would have (the 3x limit lowered so
    # that this clip's interval is beyond it)
    from d2turb.clip import strength_result  # where the note is written

    monkeypatch.setattr(strength_result, "MAX_SPAN", 1.01)
    assert main(["measure", str(clip), "--out", str(tmp_path / "blind2"), "--bootstrap", "20"]) == 0
    notes = capsys.readouterr().err.strip().splitlines()
    n = blind["narrowing"]["seeing_px"]
    flag = {"path_length_m": "--path-length M (the distance to the scene)", "ifov_rad": "--ifov RAD"}[n["by"]]
    assert len(notes) == 1 and notes[0].startswith(
        f"note: the 90 % interval of the seeing angle ρ = λ/(r0·ifov) spans {span:.1f}x; giving {flag}"
    ), notes
    assert f"narrows it most (to about {n['span_with']:.1f}x)" in notes[0] and n["span_with"] < span, notes
    monkeypatch.undo()
    # the camera given: D/r0 first, ρ beside it, r0; windows and the plot
    args = ["--window", "8", "--plot", "--bootstrap", "20", "--ifov", "2.625e-6"]
    assert main(["measure", str(clip), "--out", str(out), *args]) == 0
    captured = capsys.readouterr()
    line, notes = captured.out.strip().splitlines(), captured.err.strip().splitlines()
    assert len(line) == 1 and "D/r0 =" in line[0] and "no --path-length" in line[0]
    assert "given: ifov_rad, marginalised: footprint_px" in line[0]
    res = json.loads((out / "measure.json").read_text())
    assert res["cn2"] is None and res["dr0"] > 0 and res["dr0_ci"][0] <= res["dr0"] <= res["dr0_ci"][1]
    assert res["r0_m"] == pytest.approx(0.1 / res["dr0"])
    assert len(notes) == (res["dr0_ci"][1] / res["dr0_ci"][0] > M.MAX_SPAN), notes  # a note only beyond 3x
    assert len(res["windows"]) == 2 and (out / "measure.png").stat().st_size > 0
    # the seeing angle λ/(r0·ifov) in px: λ/(D·ifov) (2 px with this ifov and the default optics) times D/r0
    assert "seeing angle ρ = λ/(r0·ifov) = " in line[0]
    assert res["seeing_px"] == pytest.approx(2.0 * res["dr0"], rel=1e-6)
    assert res["seeing_px_ci"][0] <= res["seeing_px"] <= res["seeing_px_ci"][1] and "seeing_px" in res["windows"][0]
    assert res["answer"] == {"quantity": "dr0", "value": res["dr0"], "ci": res["dr0_ci"], "unit": ""}
    with pytest.raises(D2TurbError, match="window must be"):
        M.measure_clip(frames, window=4)
