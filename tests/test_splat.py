"""Flow inversion by density-based forward splatting (d2turb.ops.splat)."""

import warnings

import numpy as np
import pytest
import torch

from d2turb.errors import D2TurbError
from d2turb.ops import BackwardFlow, InvertFlow, backward_flow, invert_flow, splat, warp


def affine_flow(a: np.ndarray, t, h: int, w: int, dtype=torch.float64) -> torch.Tensor:
    """Δ(x) = A·x + t on the pixel grid (x = (col, row))."""
    ys, xs = torch.meshgrid(torch.arange(h, dtype=dtype), torch.arange(w, dtype=dtype), indexing="ij")
    dx = a[0, 0] * xs + a[0, 1] * ys + t[0]
    dy = a[1, 0] * xs + a[1, 1] * ys + t[1]
    return torch.stack((dx, dy))[None]


def test_constant_translation_inverts_exactly():
    flow = torch.empty(1, 2, 24, 30)
    flow[:, 0], flow[:, 1] = 1.3, -0.6
    v = invert_flow(flow)
    assert torch.allclose(v, -flow, atol=1e-6)


def test_affine_flow_matches_analytic_inverse():
    # y = x + A x + t  ⇒  x = (I + A)^-1 (y − t),  V(y) = x − y
    h, w = 48, 56
    a = np.array([[0.04, -0.06], [0.05, -0.03]])
    t = (1.7, -2.2)
    flow = affine_flow(a, t, h, w)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    inv = np.linalg.inv(np.eye(2) + a)
    px, py = xs - t[0], ys - t[1]
    vx = inv[0, 0] * px + inv[0, 1] * py - xs
    vy = inv[1, 0] * px + inv[1, 1] * py - ys
    v = invert_flow(flow)[0]
    m = 6
    err = torch.maximum((v[0] - vx).abs(), (v[1] - vy).abs())[m:-m, m:-m]
    assert err.max() < 0.02


def test_expanding_flow_has_holes_that_are_filled():
    # every source pixel lands 2.5 px from its neighbour: most target pixels receive no weight
    h, w = 40, 40
    a = np.eye(2) * 1.5
    c = (h - 1) / 2
    flow = affine_flow(a, (-1.5 * c, -1.5 * c), h, w)
    _, density = splat(flow, flow)
    assert (density < 1e-3).float().mean() > 0.2
    v = invert_flow(flow)[0]
    assert torch.isfinite(v).all()
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    vx, vy = (xs - c) * (1 / 2.5 - 1), (ys - c) * (1 / 2.5 - 1)
    err = torch.maximum((v[0] - vx).abs(), (v[1] - vy).abs())[10:-10, 10:-10]
    # filled values come from splats within ~1 px: error ≤ |∇V| · 1 px = 0.6 px (zeroth-order fill)
    assert err.max() < 0.6


def test_holes_fall_back_to_negated_forward_flow_without_filling():
    h, w = 20, 20
    flow = affine_flow(np.eye(2) * 1.5, (-14.25, -14.25), h, w)
    _, density = splat(flow, flow)
    holes = (density < 1e-3).expand(1, 2, h, w)
    v = invert_flow(flow, fill_iterations=0)
    assert holes.any() and torch.equal(v[holes], -flow[holes])


def test_splat_conserves_weight_inside_the_frame():
    g = torch.Generator().manual_seed(1)
    h, w = 16, 20
    flow = torch.rand(2, 2, h, w, generator=g, dtype=torch.float64) * 6 - 3
    acc, density = splat(torch.ones(2, 1, h, w, dtype=torch.float64), flow)

    def inside_weight(pos, n):  # bilinear weight of the two neighbours along one axis that lie in [0, n-1]
        lo = np.floor(pos)
        frac = pos - lo
        return (1 - frac) * ((lo >= 0) & (lo <= n - 1)) + frac * ((lo + 1 >= 0) & (lo + 1 <= n - 1))

    px = np.arange(w) + flow[:, 0].numpy()
    py = np.arange(h)[:, None] + flow[:, 1].numpy()
    expected = (inside_weight(px, w) * inside_weight(py, h)).sum(axis=(1, 2))
    assert np.allclose(density.sum(dim=(1, 2, 3)).numpy(), expected)
    assert torch.allclose(acc, density)


def test_batch_items_are_independent():
    g = torch.Generator().manual_seed(2)
    flow = torch.randn(3, 2, 20, 18, generator=g)
    together = invert_flow(flow)
    for i in range(3):
        assert torch.allclose(together[i : i + 1], invert_flow(flow[i : i + 1]), atol=1e-6)
    assert torch.equal(InvertFlow()(flow), together)


def test_old_names_warn_once_and_give_the_same_flow():
    flow = torch.randn(1, 2, 12, 10, generator=torch.Generator().manual_seed(4))
    with pytest.warns(DeprecationWarning, match="invert_flow"):
        old = backward_flow(flow)
    assert torch.equal(old, invert_flow(flow))
    with pytest.warns(DeprecationWarning, match="InvertFlow"):
        module = BackwardFlow()
    assert isinstance(module, InvertFlow) and torch.equal(module(flow), old)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once per process: the second use is silent
        backward_flow(flow)
        BackwardFlow()


def test_inverting_the_inverse_gives_the_forward_flow_back():
    ys, xs = torch.meshgrid(torch.arange(32.0), torch.arange(32.0), indexing="ij")
    fwd = torch.stack((1.5 * torch.sin(ys / 6), -1.2 * torch.cos(xs / 7)))[None]
    back = invert_flow(invert_flow(fwd))
    assert (back - fwd)[..., 6:-6, 6:-6].abs().max() < 0.1


def test_gradcheck():
    # fractional parts kept away from 0/1 so finite differences do not cross a bilinear kink
    g = torch.Generator().manual_seed(3)
    base = torch.randint(-1, 2, (1, 2, 4, 4), generator=g).double()
    frac = 0.3 + 0.4 * torch.rand(1, 2, 4, 4, generator=g, dtype=torch.float64)
    flow = (base + frac).requires_grad_()
    assert torch.autograd.gradcheck(lambda f: invert_flow(f), (flow,), eps=1e-6, atol=1e-5)


@pytest.mark.parametrize(
    "bad, msg",
    [
        (torch.zeros(2, 8, 8), "(B, 2, H, W)"),
        (torch.zeros(1, 3, 8, 8), "(B, 2, H, W)"),
        (torch.zeros(1, 2, 8, 8, dtype=torch.long), "floating"),
        (torch.full((1, 2, 8, 8), float("nan")), "NaN"),
    ],
)
def test_bad_input_raises_clear_error(bad, msg):
    with pytest.raises(D2TurbError, match=msg.replace("(", r"\(").replace(")", r"\)")):
        invert_flow(bad)


def _natural_images(size: int) -> torch.Tensor:
    from skimage import data, transform

    imgs = [data.astronaut(), data.coffee(), data.chelsea(), np.stack([data.camera()] * 3, -1)]
    return torch.stack(
        [
            torch.from_numpy(transform.resize(im, (size, size), anti_aliasing=True)).float().permute(2, 0, 1)
            for im in imgs
        ]
    )


@pytest.fixture(scope="module")
def simulator():
    from d2turb.sim import Simulator, TurbulenceParams

    return Simulator(TurbulenceParams(dr0=4.5, n_zernike=10, psf_grid_px=32))


def _mse(a, b, margin=8):
    return ((a - b)[..., margin:-margin, margin:-margin] ** 2).mean(dim=(1, 2, 3))


def test_splatted_flow_beats_direct_inversion_on_simulated_strong_turbulence(simulator):
    """Paper: warping I_tilt by V_bwd reproduces I better than by −Δ (0.001349 vs 0.001436)."""
    clean = _natural_images(128)
    res = simulator(clean, generator=torch.Generator().manual_seed(0))
    assert res.fwd_flow_px.abs().max() > 3  # strong turbulence: several pixels of displacement
    v = invert_flow(res.fwd_flow_px)
    mse_splat = _mse(warp(res.tilt, v), res.clean)
    mse_direct = _mse(warp(res.tilt, -res.fwd_flow_px), res.clean)
    assert (mse_splat < mse_direct).all()
    assert mse_splat.mean() < 0.7 * mse_direct.mean()


def test_splatted_flow_beats_direct_inversion_on_shared_images(shared_data, simulator):
    import torch.nn.functional as F

    from d2turb.io import read_image

    files = sorted((shared_data / "clean" / "urban100").glob("*.png"))[:3]
    if not files:
        pytest.skip("no urban100 images")
    clean = torch.stack([F.interpolate(read_image(f)[None], size=(128, 128), mode="area")[0] for f in files])
    res = simulator(clean, generator=torch.Generator().manual_seed(1))
    v = invert_flow(res.fwd_flow_px)
    assert (_mse(warp(res.tilt, v), res.clean) < _mse(warp(res.tilt, -res.fwd_flow_px), res.clean)).all()
