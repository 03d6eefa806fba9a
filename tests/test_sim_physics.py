"""The simulator's statistics against turbulence theory (docs: physics.md §1–4)."""

import math

import numpy as np
import pytest
import torch
from scipy import integrate

from d2turb.sim import Simulator, TurbulenceParams
from d2turb.sim.psf import PupilOptics
from d2turb.sim.tilt import layer_tilt_correlation, tilt_correlation
from d2turb.sim.zernike import noll_covariance, noll_to_nm, zernike

NOLL_CHECKS = {
    (2, 2): 0.4482,
    (3, 3): 0.4482,
    (4, 4): 0.02318,
    (5, 5): 0.02318,
    (6, 6): 0.02318,
    (7, 7): 0.00618,
    (8, 8): 0.00618,
    (9, 9): 0.00618,
    (10, 10): 0.00618,
    (11, 11): 0.00245,
    (2, 8): -0.0141,
    (4, 11): -0.00387,
}


def test_noll_covariance_check_values():
    cov = noll_covariance(36)
    for (j, jp), value in NOLL_CHECKS.items():
        assert cov[j - 2, jp - 2] == pytest.approx(value, rel=3e-3)
    assert np.allclose(cov, cov.T)
    assert np.linalg.eigvalsh(cov).min() > 0
    # residual after J modes, Δ_J = 1.0299 − Σ var(a_j); Noll's own table is consistent with this to ~1e-3
    assert 1.0299 - np.trace(cov[:10, :10]) == pytest.approx(0.0377, abs=1e-3)  # Δ11
    assert 1.0299 - np.trace(cov[:20, :20]) == pytest.approx(0.0208, abs=1e-3)  # Δ21


def test_noll_indices():
    assert [noll_to_nm(j) for j in range(1, 12)] == [
        (0, 0),
        (1, 1),
        (1, 1),
        (2, 0),
        (2, 2),
        (2, 2),
        (3, 1),
        (3, 1),
        (3, 3),
        (3, 3),
        (4, 0),
    ]


def test_zernike_orthonormal_on_unit_disk():
    n = 400
    c = (np.arange(n) + 0.5) / n * 2 - 1
    y, x = np.meshgrid(c, c, indexing="ij")
    rho, theta = np.hypot(x, y), np.arctan2(y, x)
    inside = rho <= 1
    z = np.stack([zernike(j, rho[inside], theta[inside]) for j in range(1, 16)])
    gram = z @ z.T / inside.sum()  # (1/π)∫_disk Z_j Z_j' by the midpoint rule
    assert np.abs(gram - np.eye(15)).max() < 0.01
    assert np.allclose(zernike(2, rho, theta), 2 * x)
    assert np.allclose(zernike(3, rho, theta), 2 * y)


def _pointwise_coefficients(sim, n, dr0, seed):
    """a_2..a_J at one pixel of n independent 2×2 images (B, J-1) in rad."""
    gen = torch.Generator().manual_seed(seed)
    chunks = []
    for _ in range(n // 20000):
        b = 20000
        d = torch.full((b,), float(dr0), dtype=torch.float64)
        tilt = sim.tilt_fields(b, 2, 2, d, gen)
        high = sim.high_fields(tilt, d, (1.0, 1.0), gen)
        chunks.append(torch.cat([tilt[:, :, 0, 0], high[:, :, 0, 0]], 1).double())
    return torch.cat(chunks).numpy()


def test_coefficient_variances_and_cross_covariances_match_noll():
    """Test 1. N = 100k independent samples: relative standard error of a variance sqrt(2/N) = 0.45 %;
    of cov(a2,a8): sqrt(var2·var8·(1+ρ²)/N)/|cov| = 1.2 %; of cov(a4,a11): 1.9 %. Tolerance 5 %."""
    dr0 = 2.0
    sim = Simulator(TurbulenceParams(dr0=dr0, n_zernike=36))
    a = _pointwise_coefficients(sim, 100_000, dr0, seed=1)
    emp = a.T @ a / len(a)
    scale = dr0 ** (5 / 3)
    for (j, jp), value in NOLL_CHECKS.items():
        assert emp[j - 2, jp - 2] == pytest.approx(value * scale, rel=0.05), (j, jp)
    assert np.abs(a.mean(0)).max() < 0.02


@pytest.mark.parametrize("dr0,ifov_factor", [(1.0, 1.0), (3.0, 1.0), (5.0, 1.0), (3.0, 2.0)])
def test_tilt_std_in_pixels(dr0, ifov_factor):
    """Test 2. N = 20000 tilt fields of 3×3 px, one pixel each: the relative standard error of a
    standard deviation is 1/sqrt(2N) = 0.5 %; tolerance 5 %."""
    lam, d = 525e-9, 0.1
    ifov = ifov_factor * lam / (2 * d)
    sim = Simulator(
        TurbulenceParams(aperture_m=d, wavelength_m=lam, dr0=dr0, ifov_rad=ifov, n_zernike=10, psf_grid_px=4)
    )
    n = 20000
    flow = (
        sim.tilt_fields(n, 3, 3, torch.full((n,), dr0), torch.Generator().manual_seed(7))[:, :, 1, 1].double()
        * sim.px_per_a2
    )
    expected = math.sqrt(0.1816) * (lam / d) / ifov * dr0 ** (5 / 6)  # = 0.852·(D/r0)^(5/6) at Nyquist
    sx, sy = flow[:, 0].std().item(), flow[:, 1].std().item()
    assert sx == pytest.approx(expected, rel=0.05)
    assert sy == pytest.approx(expected, rel=0.05)
    assert sx / sy == pytest.approx(1.0, abs=0.05)


def test_simulator_flow_is_the_tilt_field_in_pixels():
    """End to end: with no depth, SimResult.flow is the generated (a2, a3) field times 2λ/(πD)/ifov."""
    sim = Simulator(TurbulenceParams(dr0=2.5, n_zernike=15))
    img = torch.rand(3, 3, 20, 28, generator=torch.Generator().manual_seed(0))
    res = sim(img, generator=torch.Generator().manual_seed(5))
    a = sim.tilt_fields(3, 20, 28, torch.full((3,), 2.5), torch.Generator().manual_seed(5))
    assert torch.allclose(res.flow, a * sim.px_per_a2, atol=1e-5)
    assert sim.px_per_a2 == pytest.approx(4 / math.pi)  # 2λ/(πD) per unit a2 at ifov = λ/(2D)


TABLE_S = [0.1, 0.25, 0.5, 1, 2, 5, 10]
TABLE_PERP = [0.996, 0.974, 0.912, 0.780, 0.630, 0.467, 0.371]
TABLE_PAR = [0.987, 0.926, 0.772, 0.558, 0.428, 0.312, 0.247]


def test_layer_correlation_function_matches_table():
    perp, par = layer_tilt_correlation(TABLE_S)
    assert np.abs(perp - TABLE_PERP).max() < 0.003
    assert np.abs(par - TABLE_PAR).max() < 0.003


def test_generated_tilt_correlation_matches_table_single_layer():
    """Test 3 (layer geometry, s = 0.05 per pixel). The covariance the generator realises (exact,
    from its spectrum) and the empirical one from 600 fields of 224×224 px, both within 0.05 of the table.
    Empirical standard error of the structure-function estimate (spread of 6 batches of 100 fields / √6):
    0.002 (s = 1) and 0.011 (s = 5, parallel), so 0.05 is ≥ 4.5 standard errors."""
    alpha = 0.05
    p = TurbulenceParams(tilt_geometry="layer", layer_z_frac=0.5)
    p.ifov_rad = alpha * p.aperture_m * 0.5 / (p.path_length_m * 0.5)  # s per pixel = θ z / (D (1 − z/L))
    sim = Simulator(p)
    layers = sim.tilt_layers()
    assert layers[0][0] == pytest.approx(alpha)
    sampler = sim.tilt_sampler(224, 224)
    cov = sampler.implied_covariance()
    px = [round(s / alpha) for s in TABLE_S]  # 2 … 200 px
    par_x, perp_x = cov[0, px, 0, 0], cov[0, px, 1, 1]  # separation along x: x-component is parallel
    perp_y, par_y = cov[px, 0, 0, 0], cov[px, 0, 1, 1]
    for got in (par_x, par_y):
        assert np.abs(got - TABLE_PAR).max() < 0.05
    for got in (perp_x, perp_y):
        assert np.abs(got - TABLE_PERP).max() < 0.05
    fields = sampler.sample(600, torch.Generator().manual_seed(3)).double()
    for sep, exp_perp, exp_par in [(20, 0.780, 0.558), (100, 0.467, 0.312)]:
        # structure-function estimator c = 1 − E[(t(x+r) − t(x))²]/2 (variance 1 by construction)
        par = 1 - 0.5 * ((fields[:, 0, :, sep:] - fields[:, 0, :, :-sep]) ** 2).mean().item()
        perp = 1 - 0.5 * ((fields[:, 1, :, sep:] - fields[:, 1, :, :-sep]) ** 2).mean().item()
        assert par == pytest.approx(exp_par, abs=0.05)
        assert perp == pytest.approx(exp_perp, abs=0.05)
    assert (fields[:, 0, 0, 0] ** 2).mean().item() == pytest.approx(1.0, abs=0.15)  # 600 samples: SE 0.06


def test_path_geometry_is_weighted_layer_average():
    d, length = 0.1, 1000.0
    for theta in [1e-5, 1e-4, 1e-3]:
        perp, par = tilt_correlation(theta, d, length, "path")

        def layer(t, which, theta=theta):
            s = theta * length * t / (d * (1 - t))
            return layer_tilt_correlation(s)[which] * (1 - t) ** (5 / 3)

        norm = 3 / 8  # ∫ (1 − t)^(5/3) dt
        ref_perp = integrate.quad(layer, 0, 1, args=(0,), limit=200, epsabs=1e-4, epsrel=1e-4)[0] / norm
        ref_par = integrate.quad(layer, 0, 1, args=(1,), limit=200, epsabs=1e-4, epsrel=1e-4)[0] / norm
        assert float(perp) == pytest.approx(ref_perp, abs=3e-3)
        assert float(par) == pytest.approx(ref_par, abs=3e-3)


def test_path_sampler_realises_path_correlation():
    sim = Simulator(TurbulenceParams())
    cov = sim.tilt_sampler(160, 160).implied_covariance()
    px = np.array([1, 5, 20, 80, 150])
    perp, par = tilt_correlation(px * sim.params.ifov_rad, 0.1, 1000.0, "path")
    assert np.abs(cov[0, px, 0, 0] - par).max() < 0.03
    assert np.abs(cov[0, px, 1, 1] - perp).max() < 0.03


def _truncated_otf(ks, first, n_modes, cov, diam=32):
    """Independent oracle: mean OTF of a Gaussian phase = pupil overlap average of exp(−½ D_φ), with the
    structure function D_φ(x, x') = (Z(x) − Z(x'))ᵀ C (Z(x) − Z(x')) of the truncated expansion."""
    size = diam + 4
    c = np.arange(size) - (size - 1) / 2
    y, x = np.meshgrid(c, c, indexing="ij")
    rho, theta = np.hypot(x, y) / (diam / 2), np.arctan2(y, x)
    inside = rho <= 1
    z = np.stack([zernike(j, rho, theta) for j in range(first, n_modes + 1)]) * inside
    out = []
    for k in ks:
        overlap = inside[:, :-k] & inside[:, k:]
        diff = (z[:, :, :-k] - z[:, :, k:])[:, overlap]
        out.append(np.exp(-0.5 * np.einsum("in,ij,jn->n", diff, cov, diff)).sum() / inside.sum())
    return np.array(out)


@pytest.mark.parametrize("with_tilt", [True, False])
def test_mean_psf_matches_theoretical_otf(with_tilt):
    """Test 4, D/r0 = 2, Nyquist sampling, 3000 PSFs (MTF standard error ≈ 0.005).

    Tilt included: Fried's long-exposure T·H (α = 0) within 0.05. Tilt removed: short exposure (α = 1);
    36 modes miss Δ_36 ≈ 0.2944·36^(−√3/2) = 0.0132 (D/r0)^(5/3) rad² of phase variance, which raises the
    MTF by up to exp(Δ_36 (D/r0)^(5/3)) = 1.043 at D/r0 = 2, so the comparison is with T·H·1.043 (and the
    truncated-expansion oracle within 0.02)."""
    d, lam, n_modes, dr0 = 0.1, 525e-9, 36, 2.0
    first = 2 if with_tilt else 4
    optics = PupilOptics([lam], lam, d, lam / (2 * d), range(first, n_modes + 1))
    cov = np.asarray(noll_covariance(n_modes))[first - 2 :, first - 2 :] * dr0 ** (5 / 3)
    a = np.random.default_rng(0).multivariate_normal(np.zeros(len(cov)), cov, size=3000)
    psf = optics.psfs(torch.from_numpy(a).float(), 31)[0].double().mean(0)
    assert psf.sum().item() == pytest.approx(1.0, abs=1e-6)
    padded = torch.zeros(64, 64, dtype=torch.float64)
    padded[:63, :63] = psf
    otf = torch.fft.fft2(padded).abs().numpy()
    ks = np.array([2, 4, 6, 8, 10, 12, 14, 16])
    mtf = 0.5 * (otf[0, ks] + otf[ks, 0])
    f = ks / 64  # cycles per pixel; ν = f/ifov, λν/D = 2f, λν/r0 = 2f·D/r0
    u = 2 * f
    diffraction = 2 / np.pi * (np.arccos(u) - u * np.sqrt(1 - u * u))
    alpha = 0.0 if with_tilt else 1.0
    atmos = np.exp(-3.44 * (u * dr0) ** (5 / 3) * (1 - alpha * u ** (1 / 3)))
    missing = math.exp((0.2944 * n_modes ** (-math.sqrt(3) / 2)) * dr0 ** (5 / 3))
    theory = diffraction * atmos * (1.0 if with_tilt else missing)
    assert np.abs(mtf - theory).max() < 0.05
    assert np.abs(mtf - _truncated_otf(ks, first, n_modes, cov)).max() < 0.02


def test_higher_order_modes_are_correlated_in_space():
    """u_j fields of the higher modes: correlation Σ_k w_k exp(−((n+1)s_k)²) between PSF-grid nodes, so
    low orders decorrelate more slowly than high orders. 400 fields of 24×24 nodes; structure-function
    estimate, standard error < 0.01."""
    sim = Simulator(TurbulenceParams())
    spacing = (16.0, 16.0)
    sampler = sim.high_sampler(24, 24, spacing)
    u = sampler.sample(400, torch.Generator().manual_seed(11)).double()  # (400, J-3, 24, 24)
    layers = sim._separation_s(np.array([16.0]))
    for mode, n in [(0, 2), (len(sim.high_orders) - 1, 7)]:
        assert sim.high_orders[mode] == n
        expected = sum(w * np.exp(-(((n + 1) * s) ** 2)) for w, s in layers).item()
        got = 1 - 0.5 * ((u[:, mode, :, 1:] - u[:, mode, :, :-1]) ** 2).mean().item()
        assert got == pytest.approx(expected, abs=0.05)
        assert (u[:, mode] ** 2).mean().item() == pytest.approx(1.0, abs=0.1)  # large-scale part: SE ≈ 0.03
    c_low = 1 - 0.5 * ((u[:, 0, :, 1:] - u[:, 0, :, :-1]) ** 2).mean().item()
    c_high = 1 - 0.5 * ((u[:, -1, :, 1:] - u[:, -1, :, :-1]) ** 2).mean().item()
    assert c_low > c_high + 0.1
