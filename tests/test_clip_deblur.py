"""The Wiener filter's prior (d2turb.clip.deblur) against an independent computation: the squared FFT of the
finite-difference stencils it stands for (numpy's FFT of the kernels on the grid, not the closed form); the prior
and OTF chosen per path and fusion; the filter against numpy's FFT of the mirror-padded image."""

from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from d2turb.clip import PhysicsDeblur, prior_power
from d2turb.clip.deblur import (
    BALANCE_AT_2,
    LAPLACIAN_BALANCE_AT_2,
    default_balance,
    fusion_prior,
    padded_spectra,
    wiener_gain,
    wiener_padding,
)
from d2turb.clip.fusion import SHARPEST_DR0_SCALE
from d2turb.device import one_torch_thread
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


def test_spectra_made_once_serve_every_filter_of_an_image():
    """``padded_spectra`` shared by several filters (the blind deblur's ringing guard): each output is the filter's own
    to the bit, and that is numpy's Wiener filter of the mirror-padded image (the oracle: np.pad + np.fft)."""
    image = torch.rand(3, 40, 52, generator=torch.Generator().manual_seed(0))
    spectra = padded_spectra(image)
    top, bottom, left, right = wiener_padding(40, 52)
    shape = (40 + top + bottom, 52 + left + right)
    for deblur in (PhysicsDeblur(2.0, 2.0, boost_only=True), PhysicsDeblur(1.0, 1.3, prior="gradient")):
        shared = deblur(image, spectra)
        assert torch.equal(shared, deblur(image))
        gain = wiener_gain(deblur.otf(40, 52), deblur.balance, shape, deblur.prior).numpy().astype(np.float64)
        gain = np.maximum(gain, 1.0) if deblur.boost_only else gain
        for c in range(3):
            padded = np.pad(image[c].numpy().astype(np.float64), ((top, bottom), (left, right)), mode="reflect")
            want = np.fft.irfft2(np.fft.rfft2(padded) * gain, s=shape)[top : top + 40, left : left + 52]
            np.testing.assert_allclose(shared[c].numpy(), np.clip(want, 0, 1), atol=2e-5)


def test_one_torch_thread_holds_for_the_block_in_its_own_thread():
    """The physical deblurs run their torch ops on one intra-op thread; the count is the calling thread's own (a
    thread that already ran torch keeps its count) and comes back after the block."""
    before = torch.get_num_threads()
    seen, ready, asked, answered = {}, threading.Event(), threading.Event(), threading.Event()

    def other():
        seen["other, before"] = torch.get_num_threads()  # this thread's count set up (torch: at its first use)
        ready.set()
        asked.wait()
        seen["other"] = torch.get_num_threads()
        answered.set()

    torch.set_num_threads(2)
    try:
        thread = threading.Thread(target=other)
        thread.start()
        ready.wait()
        with one_torch_thread():
            seen["inside"] = torch.get_num_threads()
            asked.set()
            answered.wait()
        thread.join()
        seen["after"] = torch.get_num_threads()
    finally:
        torch.set_num_threads(before)
    assert seen == {"other, before": 2, "inside": 1, "other": 2, "after": 2}
