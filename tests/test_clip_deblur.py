"""The Wiener filter's prior (d2turb.clip.deblur) against an independent computation: the squared FFT of the
finite-difference stencils it stands for (numpy's FFT of the kernels on the grid, not the closed form); the prior
and OTF chosen per path and fusion."""

from __future__ import annotations

import numpy as np
import pytest

from d2turb.clip import PhysicsDeblur, prior_power
from d2turb.clip.deblur import (
    BALANCE_AT_2,
    LAPLACIAN_BALANCE_AT_2,
    default_balance,
    fusion_prior,
)
from d2turb.clip.fusion import SHARPEST_DR0_SCALE
from d2turb.errors import D2TurbError


def _stencil_power(kernels: list[np.ndarray], shape: tuple[int, int]) -> np.ndarray:
    """Σ |FFT(kernel)|² on the rfft2 grid of ``shape``, each kernel's centre at the origin (wrapped)."""
    total = np.zeros((shape[0], shape[1] // 2 + 1))
    for k in kernels:
        grid = np.zeros(shape)
        cy, cx = k.shape[0] // 2, k.shape[1] // 2
        for (y, x), v in np.ndenumerate(k):
            grid[(y - cy) % shape[0], (x - cx) % shape[1]] += v
        total += np.abs(np.fft.rfft2(grid)) ** 2
    return total


@pytest.mark.parametrize("shape", [(24, 30), (17, 16)])
def test_priors_are_the_power_of_their_difference_stencils(shape):
    """gradient: the forward differences along x and y; laplacian: the 5-point Laplacian."""
    dx, dy = np.array([[0.0, -1.0, 1.0]]), np.array([[0.0], [-1.0], [1.0]])
    lap = np.array([[0.0, 1.0, 0.0], [1.0, -4.0, 1.0], [0.0, 1.0, 0.0]])
    np.testing.assert_allclose(prior_power(*shape, "gradient").numpy(), _stencil_power([dx, dy], shape), atol=1e-12)
    np.testing.assert_allclose(prior_power(*shape, "laplacian").numpy(), _stencil_power([lap], shape), atol=1e-12)
    with pytest.raises(D2TurbError, match="prior"):
        prior_power(*shape, "tv")


def test_the_prior_and_otf_follow_the_fusion():
    """At a given D/r0 the Laplacian prior at its weight, after the sharpest fusion with the OTF of a weaker
    turbulence; the blind deblur's prior is the gradient after the mean and the Laplacian after the sharpest fusion."""
    mean = PhysicsDeblur.for_fusion(3.0, 2.0, "mean")
    sharpest = PhysicsDeblur.for_fusion(3.0, 2.0, "sharpest", modulation=0.8)
    laplacian_weight = LAPLACIAN_BALANCE_AT_2 * 1.5 ** (5 / 3)
    assert (mean.prior, mean.dr0, mean.balance) == ("laplacian", 3.0, pytest.approx(laplacian_weight))
    assert sharpest.prior == "laplacian" and sharpest.dr0 == pytest.approx(3.0 * SHARPEST_DR0_SCALE)
    assert sharpest.balance == pytest.approx(laplacian_weight) and sharpest.modulation == 0.8
    assert (fusion_prior("mean"), fusion_prior("sharpest")) == ("gradient", "laplacian")
    assert PhysicsDeblur(3.0).balance == default_balance(3.0) == pytest.approx(laplacian_weight)
    assert PhysicsDeblur(3.0, prior="gradient").balance == pytest.approx(BALANCE_AT_2 * 1.5 ** (5 / 3))
    with pytest.raises(D2TurbError, match="prior"):
        PhysicsDeblur(3.0, prior="tv")
