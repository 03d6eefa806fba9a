"""The tilt field's lowest frequencies (issue 14): per-pixel RMS, image-scale power and the parallel /
perpendicular correlation at every separation up to the image size, against an oracle computed here from
the published integral (conftest.PublishedTiltCorrelation), for still images (periodic synthesis +
subharmonics) and for the frames of a sequence (frozen-flow sparse spectrum).

The settling run with full statistics (4000 + 3000 fields, standard error ≤ 0.5 % on the RMS and ≤ 0.003
on the correlation) is benchmarks/lowfreq_mc.py, results in docs/simulator.md; these tests stay cheap.
"""

import math

import numpy as np
import pytest
import torch

from d2turb.sim import Simulator, TurbulenceParams
from d2turb.sim.fields import VectorFieldSampler
from d2turb.sim.sequence import FrozenFlow


def _oracle_axes(oracle, params, r):
    """Path-integrated (perpendicular, parallel) correlation at pixel separations r: evaluated every pixel
    up to 64 px and at 1.6 % steps beyond (where it changes by < 1e-3 per step), interpolated between."""
    p = params
    r = np.asarray(r, dtype=np.float64)
    table = np.unique(np.r_[np.arange(0.0, 64.0), np.geomspace(64.0, max(r.max(), 65.0), 160)])
    perp, par = oracle.path(lambda t: table * p.ifov_rad * p.path_length_m * t / (p.aperture_m * (1 - t)))
    return np.interp(r, table, perp), np.interp(r, table, par)


def _image_mean_variance(oracle, params, n, cov=None):
    """Variance of the n×n image mean of one tilt component (unit per-pixel variance): oracle, or from a
    covariance tensor in torus order (gh, gw, 2, 2)."""
    d = np.arange(-(n - 1), n)
    dy, dx = np.meshgrid(d, d, indexing="ij")
    w = np.outer(n - np.abs(d), n - np.abs(d)) / float(n) ** 4
    if cov is not None:
        return float((w * cov[dy % cov.shape[0], dx % cov.shape[1], 0, 0]).sum())
    r = np.hypot(dx, dy)
    perp, par = _oracle_axes(oracle, params, r)
    ux2 = np.where(r > 0, dx**2 / np.maximum(r, 1e-9) ** 2, 0.5)
    return float((w * (perp + (par - perp) * ux2)).sum())


@pytest.mark.parametrize("n", [256, 512])
def test_still_tilt_matches_theory_up_to_image_size(n, published_tilt):
    """The covariance the still sampler realises (exact, from its spectrum and subharmonics: no sampling
    error): c∥ and c⊥ along both axes within 0.03 of the path-integrated I0 ± I2 theory at every separation
    k = 1 … n−1 (measured ≤ 0.003), tilt RMS within 2 % (exact by construction), and the variance of the
    image-mean tilt (the image-scale power) within 2 % of theory (measured ≤ 0.1 %)."""
    params = TurbulenceParams(dr0=3.0)
    sim = Simulator(params)
    cov = sim.tilt_sampler(n, n).implied_covariance()
    k = np.arange(1, n)
    perp, par = _oracle_axes(published_tilt, params, k)
    along_x = (cov[0, k, 0, 0], cov[0, k, 1, 1])  # (parallel, perpendicular)
    along_y = (cov[k, 0, 1, 1], cov[k, 0, 0, 0])
    for got_par, got_perp in (along_x, along_y):
        assert np.abs(got_par - par).max() < 0.03
        assert np.abs(got_perp - perp).max() < 0.03
    sigma = math.sqrt(cov[0, 0, 0, 0]) * sim.tilt_std * sim.px_per_a2 * params.dr0 ** (5 / 6)
    expected = math.sqrt(0.1816) * (params.reference_wavelength / params.aperture_m) / params.ifov_rad * 3 ** (5 / 6)
    assert sigma == pytest.approx(expected, rel=0.02)
    theory = _image_mean_variance(published_tilt, params, n)
    assert _image_mean_variance(None, params, n, cov) == pytest.approx(theory, rel=0.02)


def test_periodic_synthesis_alone_overshoots_near_the_image_size(published_tilt):
    """Why the subharmonics are there: without them (torus of period 2n) the realised correlation is
    symmetric about n and overshoots theory by 0.037 at k → n on 256² (still exact in variance)."""
    params = TurbulenceParams()
    sim = Simulator(params)
    n = 256
    plain = VectorFieldSampler(n, n, sim.tilt_layers(), levels=0).implied_covariance()
    k = np.arange(1, n)
    perp, _ = _oracle_axes(published_tilt, params, k)
    assert np.abs(plain[0, k, 1, 1] - perp).max() > 0.03
    assert plain[0, 0, 0, 0] == pytest.approx(1.0, abs=1e-6)


def test_sampled_still_fields_follow_the_realised_covariance():
    """The sampler's output (FFT part + subharmonic part) has the exact covariance checked above. The code
    path does not depend on the size, so a 24×24 frame (scaled to 10× coarser pixels, so that it spans
    the separations of a 240² Nyquist image) makes many fields cheap: 2000 fields, mean square and
    the structure-function correlation at k = 4, 12, 23 against the exact covariance, within 4 standard
    errors (from 8 batch means; measured SE ≈ 0.02 on the mean square, ≤ 0.014 on the correlations; with
    80 000 fields of 12² the same comparison gives |z| ≤ 1.4)."""
    params = TurbulenceParams()
    params.ifov_rad *= 10
    n = 24
    sampler = Simulator(params).tilt_sampler(n, n)
    cov = sampler.implied_covariance()
    gen = torch.Generator().manual_seed(5)
    batches = [sampler.sample(250, gen).double() for _ in range(8)]
    ms = np.array([(f**2).mean().item() for f in batches])
    assert abs(ms.mean() - 1.0) < 4 * ms.std(ddof=1) / math.sqrt(len(ms)) + 1e-3
    for k in (4, 12, n - 1):
        for comp, axis, exact in ((0, -1, cov[0, k, 0, 0]), (1, -1, cov[0, k, 1, 1]), (1, -2, cov[k, 0, 1, 1])):
            est = []
            for f in batches:
                f = f[:, comp]
                d = f[..., k:] - f[..., :-k] if axis == -1 else f[..., k:, :] - f[..., :-k, :]
                est.append(1 - 0.5 * (d**2).mean().item())
            se = np.std(est, ddof=1) / math.sqrt(len(est))
            assert se < 0.02
            assert abs(np.mean(est) - exact) < 4 * se + 1e-3, (k, comp, axis)


@pytest.mark.parametrize("n", [256, 512])
def test_sequence_tilt_matches_theory_up_to_image_size(n, published_tilt):
    """Frames of a sequence (frozen-flow sparse spectrum: no period, no missing low frequencies). Given its
    plane-wave frequencies, a sequence's tilt covariance is Σ_m P_m ν̂ν̂ᵀ cos(2π f_m·r) (``tilt_covariance``,
    the average over amplitudes); its variance is exactly 1 for every sequence, and the mean over 24
    independent sequences is within 0.03 of theory at every separation k = 1 … n−1 along x and y
    (measured ≤ 0.004; standard error over sequences ≤ 0.003, asserted < 0.0075)."""
    params = TurbulenceParams(dr0=3.0)
    state = FrozenFlow(Simulator(params), 24, 1, 1, generator=torch.Generator().manual_seed(0), high_waves=0)
    k = np.arange(0, n)
    perp, par = _oracle_axes(published_tilt, params, k[1:])
    for offsets, (i_par, i_perp) in ((np.stack([0 * k, k], 1), (0, 1)), (np.stack([k, 0 * k], 1), (1, 0))):
        # (24, n, 2, 2), 16 separations at a time: all n at once hold ~0.2 GB of (sequence, wave, separation) phases
        cov = np.concatenate([state.tilt_covariance(offsets[i : i + 16]).numpy() for i in range(0, n, 16)], 1)
        assert np.abs(cov[:, 0] - np.eye(2)).max() < 1e-9  # RMS exact for every sequence
        got_par, got_perp = cov[:, 1:, i_par, i_par], cov[:, 1:, i_perp, i_perp]
        for got, expected in ((got_par, par), (got_perp, perp)):
            assert (got.std(0, ddof=1) / math.sqrt(len(got))).max() < 0.0075
            assert np.abs(got.mean(0) - expected).max() < 0.03


def test_sequence_frames_have_the_covariance_of_their_waves(published_tilt):
    """The synthesised frames (plane waves through the non-uniform FFT) carry the covariance above: 64²
    frames of 48 sequences with pixels 8× coarser than Nyquist, 2 frames each (decorrelated by a fast
    wind); mean square within 4 SE of 1, and c∥, c⊥ at k = 2, 8 px within 4 SE + 0.005 of theory
    (6 batch means; measured SE ≈ 0.06 on the mean square, ≤ 0.006 on these correlations)."""
    params = TurbulenceParams(dr0=3.0)
    params.ifov_rad *= 8
    sim = Simulator(params)
    n, gen = 64, torch.Generator().manual_seed(1)
    batches = []
    for _ in range(6):
        state = FrozenFlow(sim, 8, n, n, fps=10.0, wind=20.0, generator=gen, high_waves=0)
        frames = [state.tilt(8, n, n).double()]
        state.advance(gen)
        batches.append(torch.cat(frames + [state.tilt(8, n, n).double()]))
    ms = np.array([(f**2).mean().item() for f in batches])
    assert abs(ms.mean() - 1.0) < 4 * ms.std(ddof=1) / math.sqrt(len(ms))
    ks = np.array([2, 8])
    perp, par = _oracle_axes(published_tilt, params, ks)
    for i, k in enumerate(ks):
        for comp, axis, expected in ((0, -1, par[i]), (1, -1, perp[i]), (1, -2, par[i]), (0, -2, perp[i])):
            est = []
            for f in batches:
                f = f[:, comp]
                d = f[..., k:] - f[..., :-k] if axis == -1 else f[..., k:, :] - f[..., :-k, :]
                est.append(1 - 0.5 * (d**2).mean().item())
            se = np.std(est, ddof=1) / math.sqrt(len(est))
            assert abs(np.mean(est) - expected) < 4 * se + 0.005, (k, comp, axis)
