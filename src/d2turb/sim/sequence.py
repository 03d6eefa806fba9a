"""Turbulence in time: frozen-flow layers carried by the wind, with optional boiling (docs/simulator.md).

Taylor's hypothesis per layer: the path is cut into ``n_layers`` thin layers (Gauss–Legendre nodes of the
(1 − z/L)^(5/3)-weighted path, as for the spatial statistics). Layer k at distance z_k sees two image
points θ apart θz_k apart inside a beam footprint D(1 − z_k/L), so in the normalised separation s its
tilt field is G_k(α_k x), α_k = ifov·z_k/(D(1 − z_k/L)) per pixel; a transverse wind v_k moves the layer
by v_k·Δt between frames, s = v_k·Δt/(D(1 − z_k/L)) = β_k. Frame t therefore sees G_k(α_k x − β_k ŵ t)
and the tilt at one pixel decorrelates in time exactly as two image points separated along the wind.

Each layer's field is a sum of plane waves (a sparse spectrum, Charnotskii 2013): frequencies on rings
spaced logarithmically from 1e-9 to 3 cycles per unit s, ``n_angles`` regularly spaced directions per ring
with a random rotation, radii drawn from the layer spectrum inside each ring; every wave carries its ring's
exact power. The ensemble covariance is therefore exactly the layer's I0 ± I2 correlation at every
separation, in space and in time, with no period and no missing low frequencies, and a translation is a
phase rotation, so the state (a few thousand complex amplitudes) does not grow with the number of frames.
Higher Zernike orders use the same layers: the unit fields u_j of the single-frame model (correlation
Σ_k w_k exp(−((n_j+1)s_k)²)) become plane waves with Gaussian-distributed frequencies that the wind moves
in the same way. Boiling X ∈ [0, 1] refreshes a fraction X of every wave's variance per frame:
c ← √(1−X)·c·e^{−iφ} + √X·c_new (AR(1) in the spectral coefficients); X = 1 gives independent frames.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch

from d2turb.errors import D2TurbError
from d2turb.ops.checks import check_shape
from d2turb.sim.fields import PlaneWaveGrid
from d2turb.sim.tilt import layer_tilt_radial_cdf, path_nodes

if TYPE_CHECKING:  # the simulator's module imports this one
    from d2turb.sim.simulator import SimResult

# ring edges in cycles per unit s: sparse below 0.01 (25 % of the power, nearly uniform over an image),
# dense where the structure visible in a frame lives
RING_EDGES = np.concatenate([np.geomspace(1e-9, 1e-2, 22), np.geomspace(1e-2, 3.0, 21)[1:]])


def wind_speeds(wind, z_frac: np.ndarray) -> np.ndarray:
    """Wind speed (m/s) at each layer position z/L: one number (uniform), speeds at evenly spaced points
    from the aperture (z/L = 0) to the object (z/L = 1) interpolated linearly, or a function of z/L."""
    z_frac = np.asarray(z_frac, dtype=np.float64)
    if callable(wind):
        v = np.asarray(wind(z_frac), dtype=np.float64) * np.ones_like(z_frac)
    else:
        values = np.atleast_1d(np.asarray(wind, dtype=np.float64))
        if values.ndim != 1 or values.size == 0:
            raise D2TurbError(f"wind must be a speed or a list of speeds in m/s, got {wind!r}")
        v = (
            values[0] * np.ones_like(z_frac)
            if values.size == 1
            else np.interp(z_frac, np.linspace(0, 1, values.size), values)
        )
    if not np.isfinite(v).all() or (v < 0).any():
        given = "a function" if callable(wind) else np.atleast_1d(np.asarray(wind, dtype=np.float64)).tolist()
        raise D2TurbError(f"wind speeds must be finite and >= 0 m/s, got {given}")
    return v


def check_sequence_args(frames, fps: float, wind_dir: float, boil: float) -> None:
    if frames is not None and (not isinstance(frames, int) or isinstance(frames, bool) or frames < 1):
        raise D2TurbError(f"frames must be a positive integer, got {frames!r}")
    if not math.isfinite(float(fps)) or float(fps) <= 0:
        raise D2TurbError(f"fps must be positive and finite, got {fps!r}")
    if not math.isfinite(float(wind_dir)):
        raise D2TurbError(f"wind direction must be finite, got {wind_dir!r}")
    if not math.isfinite(float(boil)) or not 0.0 <= float(boil) <= 1.0:
        raise D2TurbError(f"boil must be in [0, 1], got {boil!r}")


def _uniform(shape, generator, device) -> torch.Tensor:
    gen_device = generator.device if generator is not None else torch.device("cpu")
    return torch.rand(shape, generator=generator, device=gen_device, dtype=torch.float64).to(device)


def _phasor(angle: np.ndarray) -> torch.Tensor:
    a = torch.from_numpy(np.ascontiguousarray(angle))
    return torch.polar(torch.ones_like(a), a)


def _normal(shape, generator, device) -> torch.Tensor:
    gen_device = generator.device if generator is not None else torch.device("cpu")
    return torch.randn(shape, generator=generator, device=gen_device, dtype=torch.float64).to(device)


class FrozenFlow:
    """Unit random fields of ``batch`` independent turbulent sequences, advanced frame by frame.

    Args:
        sim: the :class:`~d2turb.sim.Simulator` whose geometry (aperture, path, ifov, layers, Zernike
            modes) the fields follow.
        batch, height, width: number of sequences and frame size in pixels.
        fps: frames per second (Δt = 1/fps).
        wind: m/s; one value, speeds at evenly spaced points from the aperture to the object, or a
            function of z/L (see :func:`wind_speeds`).
        wind_dir: direction (degrees) in which the turbulence drifts across the image, 0 = +x (right),
            90 = +y (down).
        boil: fraction of each layer's variance refreshed per frame, in [0, 1].
        n_layers: layers of the path (Gauss–Legendre nodes; "layer" geometry: the single layer).
        n_angles: plane waves per ring of the tilt spectrum; high_waves: per higher-order mode and layer.

    ``tilt(B, H, W)`` gives the unit tilt fields (B, 2, H, W) of the current frame, ``high(gh, gw, spacing)``
    the unit higher-order fields on the PSF nodes (B, J−3, gh, gw); ``advance(generator)`` moves to the next
    frame. Memory does not depend on the number of frames.
    """

    def __init__(
        self,
        sim,
        batch: int,
        height: int,
        width: int,
        fps: float = 30.0,
        wind=1.0,
        wind_dir: float = 0.0,
        boil: float = 0.0,
        generator: torch.Generator | None = None,
        n_layers: int = 12,
        n_angles: int = 8,
        high_waves: int = 16,
    ):
        check_sequence_args(None, fps, wind_dir, boil)
        p = sim.params
        self.batch, self.height, self.width = batch, height, width
        self.device = sim.device
        self.boil = float(boil)
        dev = self.device
        t, w = path_nodes(p.tilt_geometry, p.layer_z_frac, n_layers)
        alpha = np.array([a for a, _ in sim.tilt_layers(len(t))])  # s per pixel of separation
        speed = wind_speeds(wind, t)
        beta = speed / float(fps) / (p.aperture_m * (1 - t))  # s per frame (layer shift v·Δt / footprint)
        phi = math.radians(float(wind_dir))
        wind_hat = np.array([math.sin(phi), math.cos(phi)])  # (y, x)
        self.layers = dict(z_frac=t, weight=w, alpha=alpha, beta=beta, speed=speed)
        k = len(t)

        # ---- tilt: rings of plane waves per layer (B, K, R, A)
        nu_tab, cdf_tab = layer_tilt_radial_cdf()
        edges_cdf = np.interp(RING_EDGES, nu_tab, cdf_tab)
        lo = np.concatenate([[0.0], edges_cdf[:-1]])
        hi = np.concatenate([edges_cdf[:-1], [1.0]])  # the last ring takes the tail beyond 3
        r, a = len(lo), int(n_angles)
        u = _uniform((batch, k, r, a), generator, dev).cpu().numpy()
        radius = np.interp(lo[:, None] + u * (hi - lo)[:, None], cdf_tab, nu_tab)  # inverse CDF inside the ring
        theta = _uniform((batch, k, r, 1), generator, dev).cpu().numpy() * (np.pi / a) + np.pi * np.arange(a) / a
        nu = np.stack([radius * np.sin(theta), radius * np.cos(theta)], -1)  # (B, K, R, A, 2) as (y, x)
        power = np.broadcast_to(((hi - lo) * 2.0 / a)[None, :, None], (k, r, a)) * w[:, None, None]
        self._tilt_sd = torch.from_numpy(np.sqrt(power)).reshape(1, -1).to(dev)  # (1, M); Σ power = 2 (trace)
        nu = nu.reshape(batch, k, r * a, 2)
        freqs = nu * alpha[None, :, None, None]  # cycles per pixel
        along = (nu @ wind_hat) * beta[None, :, None]  # cycles per frame
        self._tilt_along = torch.from_numpy(along.reshape(batch, -1)).to(dev)
        self._tilt_step = _phasor(-2 * np.pi * along.reshape(batch, -1)).to(dev)
        self._tilt_dir = torch.from_numpy(np.exp(1j * theta).reshape(batch, -1)).to(dev)  # x + iy of ν̂
        self._tilt_amp = self._tilt_draw(generator)
        freqs = torch.from_numpy(freqs.reshape(batch, -1, 2)).to(dev)
        self._tilt_freqs = freqs
        self._grid = PlaneWaveGrid(height, width, half_width=4)
        self._plan = self._grid.plan(torch.cat([freqs, -freqs], 1))

        # ---- higher orders: Gaussian-spectrum plane waves per mode j and layer (B, J', K, M_h)
        orders = np.array(sim.high_orders, dtype=np.float64)
        self.n_high = len(orders) if high_waves > 0 else 0
        if self.n_high:
            sigma = (orders + 1) / (math.sqrt(2) * math.pi)  # exp(−a²s²) ⇔ ν ~ N(0, a²/(2π²)) per axis
            g = _normal((batch, self.n_high, k, high_waves, 2), generator, dev).cpu().numpy()
            nu_h = g * sigma[None, :, None, None, None]
            self._high_freqs = torch.from_numpy(
                (nu_h * alpha[None, None, :, None, None]).reshape(batch, self.n_high, -1, 2)
            )
            along_h = (nu_h @ wind_hat) * beta[None, None, :, None]
            self._high_step = _phasor(-2 * np.pi * along_h.reshape(batch, self.n_high, -1)).to(dev)
            sd = np.sqrt(np.broadcast_to(w[:, None] / high_waves, (k, high_waves)).reshape(-1))
            self._high_sd = torch.from_numpy(sd).to(dev)
            self._high_amp = self._high_draw(generator)
            self._high_freqs = self._high_freqs.to(dev)
        self._high_basis: dict = {}
        self.frame = 0

    # ---- amplitudes: c ~ CN(0, 2·power), so Re(c·e^{iφ}) has variance `power`
    def _tilt_draw(self, generator) -> torch.Tensor:
        g = _normal((self.batch, self._tilt_sd.shape[1], 2), generator, self.device)
        return torch.complex(g[..., 0], g[..., 1]) * self._tilt_sd

    def _high_draw(self, generator) -> torch.Tensor:
        g = _normal((self.batch, self.n_high, self._high_sd.shape[0], 2), generator, self.device)
        return torch.complex(g[..., 0], g[..., 1]) * self._high_sd

    def tilt(self, batch: int, height: int, width: int) -> torch.Tensor:
        """Unit tilt fields (B, 2, H, W) of the current frame, x then y component."""
        if (batch, height, width) != (self.batch, self.height, self.width):
            raise D2TurbError(
                f"frame of {batch}×{height}×{width} does not match the sequence "
                f"({self.batch}×{self.height}×{self.width})"
            )
        # Z = t_x + i t_y = Σ Re(c e^{2πi f·x})·ν̂ = Σ ½c ν̂ e^{2πi f·x} + ½c̄ ν̂ e^{−2πi f·x}
        half = 0.5 * self._tilt_dir
        z = self._grid(self._plan, torch.cat([half * self._tilt_amp, half * self._tilt_amp.conj()], 1))
        return torch.stack([z.real, z.imag], 1)

    def tilt_covariance(self, offsets, lags=None) -> torch.Tensor:
        """Covariance (B, N, 2, 2) of each sequence's unit tilt between pixel x, frame t and pixel x + r,
        frame t + T, for ``offsets`` r (N, 2) px (y, x) and ``lags`` T (N,) frames (default 0), given the
        sequence's plane waves (the average over their amplitudes):
        Σ_m P_m ν̂ν̂ᵀ cos(2π(f_m·r − a_m T))·(1 − boil)^(T/2), a_m = β_k ν_m·ŵ cycles per frame.
        Its mean over sequences is the layer-averaged I0 ± I2 correlation at s = α_k r − β_k ŵ T."""
        r = torch.as_tensor(offsets, dtype=torch.float64, device=self.device).reshape(-1, 2)
        lag = torch.zeros(len(r), dtype=torch.float64, device=self.device) if lags is None else lags
        lag = torch.as_tensor(lag, dtype=torch.float64, device=self.device).reshape(-1)
        power = self._tilt_sd[0] ** 2
        d = self._tilt_dir
        terms = torch.stack([d.real * d.real, d.real * d.imag, d.imag * d.imag], -1) * power[:, None]  # (B, M, 3)
        parts = []
        step = max(1, 2**22 // self._tilt_freqs[..., 0].numel())  # offsets per chunk: (B, M, step) ≈ 32 MB
        for i in range(0, len(r), step):
            ri, li = r[i : i + step], lag[i : i + step]
            phase = self._tilt_freqs @ ri.T - self._tilt_along[..., None] * li  # (B, M, n)
            cos = torch.cos(2 * math.pi * phase) * (1.0 - self.boil) ** (li / 2)
            parts.append(torch.einsum("bmc,bmn->cbn", terms, cos))
        xx, xy, yy = torch.cat(parts, -1) if parts else terms.new_zeros(3, len(terms), 0)
        return torch.stack([torch.stack([xx, xy], -1), torch.stack([xy, yy], -1)], -2)

    def high(self, gh: int, gw: int, spacing) -> torch.Tensor:
        """Unit higher-order fields (B, J−3, gh, gw) at the PSF nodes (node i at i·spacing px)."""
        if not self.n_high:
            return torch.zeros(self.batch, 0, gh, gw, device=self.device)
        key = (gh, gw, tuple(float(s) for s in spacing))
        if key not in self._high_basis:
            ys = torch.arange(gh, dtype=torch.float64, device=self.device) * key[2][0]
            xs = torch.arange(gw, dtype=torch.float64, device=self.device) * key[2][1]
            f = self._high_freqs
            ey = torch.polar(torch.ones_like(f[..., 0, None]), 2 * math.pi * f[..., 0, None] * ys)  # (B, J', M, gh)
            ex = torch.polar(torch.ones_like(f[..., 1, None]), 2 * math.pi * f[..., 1, None] * xs)  # (B, J', M, gw)
            self._high_basis = {key: (ey.to(torch.complex64), ex.to(torch.complex64))}
        ey, ex = self._high_basis[key]
        amp = self._high_amp.to(torch.complex64)
        return ((amp[..., None] * ey).transpose(-1, -2) @ ex).real

    def advance(self, generator: torch.Generator | None = None) -> None:
        """Move every layer by one frame (phase rotation), then boil."""
        self._tilt_amp = self._tilt_amp * self._tilt_step
        if self.n_high:
            self._high_amp = self._high_amp * self._high_step
        if self.boil > 0:
            keep, fresh = math.sqrt(1.0 - self.boil), math.sqrt(self.boil)
            self._tilt_amp = keep * self._tilt_amp + fresh * self._tilt_draw(generator)
            if self.n_high:
                self._high_amp = keep * self._high_amp + fresh * self._high_draw(generator)
        self.frame += 1


def _frames(source) -> tuple[Callable[[int], object], bool]:
    """A tensor (or a function of the frame) → the same every frame; a list/iterator → one per frame."""
    if source is None or isinstance(source, torch.Tensor) or callable(source):
        return (lambda _t: source), False
    if isinstance(source, Sequence):
        items = list(source)
        return (lambda t: items[t] if t < len(items) else StopIteration), True
    iterator = iter(source)

    def nxt(_t):
        try:
            return next(iterator)
        except StopIteration:
            return StopIteration

    return nxt, True


def simulate_sequence(
    sim,
    image,
    frames: int | None = None,
    fps: float = 30.0,
    wind=1.0,
    wind_dir: float = 0.0,
    boil: float = 0.0,
    depth=None,
    dr0=None,
    generator: torch.Generator | None = None,
    n_layers: int = 12,
) -> Iterator[SimResult]:
    """Physically correlated frames: frozen-flow layers moved by the wind; also ``Simulator.sequence`` (the same
    function, ``sim`` its simulator). Arguments are checked at once, frames are computed on demand.

    Args:
        sim: the :class:`~d2turb.sim.Simulator`.
        image: (B, C, H, W) or (C, H, W) still scene, or an iterable of such frames (a moving input).
        frames: number of frames (default: as many as the iterable gives).
        fps: frames per second. wind: m/s, one value, several (from the aperture to the object,
            interpolated) or a function of z/L. wind_dir: drift direction in degrees (0 = +x, 90 = +y).
        boil: fraction of each layer's variance refreshed per frame (0 = pure frozen flow, 1 = independent).
        depth: as for a single frame: a tensor for all frames, an iterable (one per frame), or a
            function of the (C, H, W) frame returning its depth.
        dr0, generator: as for a single frame; D/r0 is constant along the sequence.
        n_layers: layers of the path (:class:`FrozenFlow`).
    Returns:
        an iterator of :class:`~d2turb.sim.SimResult`, one per frame, computed on demand (constant memory).
    """
    check_sequence_args(frames, fps, wind_dir, boil)
    wind_speeds(wind, np.linspace(0, 1, 3))
    get_image, moving = _frames(image)
    get_depth, _ = _frames(depth)
    if not moving and frames is None:
        raise D2TurbError("frames is required for a still image")

    def new_fields(batch: int, height: int, width: int) -> FrozenFlow:
        return FrozenFlow(sim, batch, height, width, fps, wind, wind_dir, boil, generator, n_layers=n_layers)

    return _run(sim, get_image, get_depth, frames, dr0, generator, new_fields)


def _run(sim, get_image, get_depth, frames, dr0, generator, new_fields):
    state = None
    t = 0
    while frames is None or t < frames:
        img = get_image(t)
        if img is StopIteration:
            break
        dep = get_depth(t)
        if dep is StopIteration:
            raise D2TurbError(f"depth ran out at frame {t}")
        if callable(dep):
            dep = dep(img[0] if img.ndim == 4 else img)
        check_shape(img, "[B] C H W", f"frame {t}: image")
        if img.ndim == 3:
            img = img[None]
        if state is None:
            b, _, h, w = img.shape
            state = new_fields(b, h, w)
        else:
            state.advance(generator)
        yield sim(img, depth=dep, dr0=dr0, generator=generator, fields=state)
        t += 1
