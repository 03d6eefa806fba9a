"""Depth-aware Zernike-based turbulence simulator (paper Eq. 1–7)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from d2turb.deprecation import warn_once
from d2turb.errors import D2TurbError
from d2turb.ops.checks import check_shape
from d2turb.ops.warp import warp
from d2turb.sim.fields import ScalarFieldSampler, VectorFieldSampler
from d2turb.sim.params import MAX_DR0, TurbulenceParams, depth_modulation
from d2turb.sim.psf import PupilPSF, blur_with_basis, pca_basis
from d2turb.sim.sequence import simulate_sequence
from d2turb.sim.tilt import path_nodes
from d2turb.sim.zernike import noll_covariance, noll_to_nm


@dataclass
class SimResult:
    """One realisation, all tensors batched.

    Shape:
        turb, tilt, clean, blur: (B, C, H, W); fwd_flow_px: (B, 2, H, W), the forward displacement Δ in pixels, x then
        y (tilt = warp(clean, fwd_flow_px); :func:`d2turb.ops.invert_flow` gives the backward flow that undoes it);
        modulation M: (B, 1, H, W); dr0: (B,).
    """

    turb: torch.Tensor
    tilt: torch.Tensor
    clean: torch.Tensor
    fwd_flow_px: torch.Tensor
    modulation: torch.Tensor
    dr0: torch.Tensor
    blur: torch.Tensor

    @property
    def flow(self) -> torch.Tensor:
        """Deprecated name of :attr:`fwd_flow_px` (warns once)."""
        warn_once("SimResult.flow", "SimResult.flow is deprecated; use SimResult.fwd_flow_px (the forward Δ in px)")
        return self.fwd_flow_px


class Simulator:
    """Callable simulator: ``Simulator(params, device)(image, depth=None, dr0=None, generator=None)``.

    Zernike coefficient fields a_2..a_J follow Noll's covariance (cross terms included) at every
    pixel; tilt (a_2, a_3) has the exact perpendicular/parallel spatial correlation of the chosen
    geometry; higher orders a_j = B·[a2, a3] + L·u_j where u_j are unit fields with correlation
    Σ_k w_k exp(−((n_j+1) s_k)²) (width shrinking with the radial order n_j). Exact PSFs from these
    coefficients on a grid every ``psf_grid_px`` pixels are compressed to a PCA basis and applied as a
    spatially varying blur; tilt becomes the displacement field Δ.

    Args:
        params: the imaging and turbulence parameters (default ``TurbulenceParams()``: D/r0 = 3, Nyquist pixels).
        device: where the fields and the blur are computed.

    Example:
        >>> sim = Simulator(TurbulenceParams(dr0=2.0))
        >>> out = sim(torch.rand(1, 3, 64, 64), generator=torch.Generator().manual_seed(0))
        >>> out.turb.shape, out.fwd_flow_px.shape
        (torch.Size([1, 3, 64, 64]), torch.Size([1, 2, 64, 64]))
    """

    def __init__(self, params: TurbulenceParams | None = None, device="cpu"):
        self.params = p = params if params is not None else TurbulenceParams()
        self.device = torch.device(device)
        cov = np.asarray(noll_covariance(p.n_zernike))  # j = 2..J, D/r0 = 1
        c_tt, c_ht, c_hh = cov[:2, :2], cov[2:, :2], cov[2:, 2:]
        self.tilt_std = math.sqrt(c_tt[0, 0])  # rad at λ_ref for D/r0 = 1 (0.4482^(1/2))
        self.high_from_tilt = torch.from_numpy(c_ht @ np.linalg.inv(c_tt)).float()  # B = C_ht C_tt^-1
        cond = c_hh - c_ht @ np.linalg.solve(c_tt, c_ht.T)
        self.high_chol = torch.from_numpy(np.linalg.cholesky(cond)).float() if cond.size else torch.zeros(0, 0)
        self.high_orders = [noll_to_nm(j)[0] for j in range(4, p.n_zernike + 1)]
        # tilt angle per unit a2 (Noll Z2 = 2ρcosθ): 2λ/(πD) rad, then in pixels
        self.px_per_a2 = 2 * p.reference_wavelength / (math.pi * p.aperture_m) / p.ifov_rad
        self._pupils: dict = {}
        self.pupil = self.pupil_for(0)
        self._samplers: dict = {}

    def pupil_for(self, half_window: int) -> PupilPSF:
        """The PSFs of the params' optics, in an array that holds a (2·half_window+1)² window (64 px, or more for
        strong turbulence, which also samples the pupil more finely)."""
        size = max(64, 2 * (half_window + 1))
        size = 1 << (size - 1).bit_length() if size > 64 else size
        if size not in self._pupils:
            p = self.params
            self._pupils[size] = PupilPSF(p.optics, range(4, p.n_zernike + 1), self.device, min_size=size)
        return self._pupils[size]

    # ---- random fields -------------------------------------------------------------------------
    def _separation_s(self, r_px: np.ndarray) -> list[tuple[np.ndarray, float]]:
        """[(s at each pixel separation r, weight)] over the layers of the geometry (order of tilt_layers)."""
        return [(alpha * r_px, wk) for alpha, wk in self.tilt_layers()]

    def tilt_layers(self, n_layers: int = 48) -> list[tuple[float, float]]:
        """[(s per pixel of separation, weight)] of the layers of the geometry."""
        p = self.params
        t, w = path_nodes(p.tilt_geometry, p.layer_z_frac, n_layers)
        return [(p.ifov_rad * p.path_length_m * tk / (p.aperture_m * (1 - tk)), wk) for tk, wk in zip(t, w)]

    def tilt_sampler(self, height: int, width: int) -> VectorFieldSampler:
        key = ("tilt", height, width)
        if key not in self._samplers:
            self._samplers[key] = VectorFieldSampler(height, width, self.tilt_layers())
        return self._samplers[key]

    def high_sampler(self, gh: int, gw: int, spacing: tuple[float, float]) -> ScalarFieldSampler:
        key = ("high", gh, gw, spacing)
        if key not in self._samplers:

            def corr_for(n):
                return lambda r: sum(wk * np.exp(-(((n + 1) * s) ** 2)) for s, wk in self._separation_s(r))

            self._samplers[key] = ScalarFieldSampler(gh, gw, [corr_for(n) for n in self.high_orders], spacing)
        return self._samplers[key]

    def tilt_fields(
        self, batch: int, height: int, width: int, dr0: torch.Tensor, generator=None, unit=None
    ) -> torch.Tensor:
        """a2, a3 fields (B, 2, H, W) in rad at λ_ref (from ``unit`` fields when given, else fresh ones)."""
        if unit is None:
            unit = self.tilt_sampler(height, width).sample(batch, generator, self.device)
        return unit * (self.tilt_std * dr0.to(unit).pow(5 / 6))[:, None, None, None]

    def high_fields(
        self, tilt_at_nodes: torch.Tensor, dr0: torch.Tensor, spacing, generator=None, unit=None
    ) -> torch.Tensor:
        """a4..aJ (B, J-3, gh, gw) given a2, a3 at the nodes (B, 2, gh, gw); Noll's joint covariance."""
        b, _, gh, gw = tilt_at_nodes.shape
        u = self.high_sampler(gh, gw, spacing).sample(b, generator, self.device) if unit is None else unit
        scale = dr0.to(u).pow(5 / 6)[:, None, None, None]
        bt = torch.einsum("hk,bkyx->bhyx", self.high_from_tilt.to(u), tilt_at_nodes)
        return bt + scale * torch.einsum("hk,bkyx->bhyx", self.high_chol.to(u), u)

    # ---- simulation ----------------------------------------------------------------------------
    def _dr0_vector(self, dr0, batch: int) -> torch.Tensor:
        if dr0 is None:
            v = torch.full((batch,), self.params.dr0, dtype=torch.float64)
        elif isinstance(dr0, torch.Tensor):
            v = dr0.detach().to("cpu", torch.float64).reshape(-1)
            if v.numel() == 1:
                v = v.expand(batch)
            if v.numel() != batch:
                raise D2TurbError(f"dr0 has {v.numel()} values for a batch of {batch}")
        else:
            v = torch.full((batch,), float(dr0), dtype=torch.float64)
        if not torch.isfinite(v).all() or (v <= 0).any() or (v > MAX_DR0).any():
            raise D2TurbError(f"D/r0 must be in (0, {MAX_DR0:g}], got {v.tolist()}")
        return v.clone()

    def __call__(
        self,
        image: torch.Tensor,
        depth: torch.Tensor | None = None,
        dr0=None,
        generator: torch.Generator | None = None,
        fields=None,
    ) -> SimResult:
        """One realisation of turbulence over ``image``.

        Args:
            image: the clean image(s), float in [0, 1].
            depth: depth (or a per-pixel modulation source) for the depth modulation M of Eq. 4; None: M = 1.
            dr0: D/r0, a number or one per image (default: the parameters').
            generator: the random generator of the fields (reproducible realisations).
            fields: a :class:`~d2turb.sim.sequence.FrozenFlow` supplying the unit random fields of the current
                frame of a sequence instead of fresh independent ones.

        Returns:
            A :class:`SimResult`: ``turb`` (the turbulent image), ``tilt`` (tilt only), ``clean``, ``blur``,
            ``fwd_flow_px`` (the forward displacement Δ in px), ``modulation`` and ``dr0``.

        Shape:
            - image: :math:`(C, H, W)` or :math:`(B, C, H, W)`; depth: :math:`(H, W)` or :math:`(B, 1, H, W)`.
            - turb, tilt, clean, blur: :math:`(B, C, H, W)`; fwd_flow_px: :math:`(B, 2, H, W)`; dr0: :math:`(B,)`.
        """
        check_shape(image, "[B] C H W", "image", floating=True)
        if image.ndim == 3:
            image = image[None]
        if not torch.isfinite(image).all():
            raise D2TurbError("image contains NaN or infinite values")
        b, c, h, w = image.shape
        if h < 2 or w < 2 or b < 1:
            raise D2TurbError(f"image is too small: {tuple(image.shape)}")
        n_wl = len(self.pupil.channels)
        if n_wl > 1 and c != n_wl:
            raise D2TurbError(f"image has {c} channels but {n_wl} wavelengths are set")
        image = image.to(self.device)
        p = self.params
        dr0 = self._dr0_vector(dr0, b)

        modulation = depth_modulation(self._check_depth(depth, b, h, w), p.modulation, p.offset_s)
        if modulation is None:
            modulation = torch.ones(b, 1, h, w, device=self.device, dtype=image.dtype)

        unit = None if fields is None else fields.tilt(b, h, w)
        a_tilt = self.tilt_fields(b, h, w, dr0, generator, unit)  # (B, 2, H, W)
        fwd_flow0_px = a_tilt * self.px_per_a2  # Δ0 in pixels, x then y

        # exact PSFs on a coarse grid of nodes spanning the image corners
        gh, gw = max(2, math.ceil((h - 1) / p.psf_grid_px) + 1), max(2, math.ceil((w - 1) / p.psf_grid_px) + 1)
        ys = torch.linspace(0, h - 1, gh, device=self.device).round().long()
        xs = torch.linspace(0, w - 1, gw, device=self.device).round().long()
        tilt_nodes = a_tilt[:, :, ys][:, :, :, xs]
        spacing = ((h - 1) / (gh - 1), (w - 1) / (gw - 1))
        unit = None if fields is None else fields.high(gh, gw, spacing)
        a_high = self.high_fields(tilt_nodes, dr0, spacing, generator, unit)  # (B, J-3, gh, gw)
        coeffs = a_high.permute(0, 2, 3, 1).reshape(b * gh * gw, -1)
        # window half-width (2.5·D/r0 + 3)·λ/D: ≥ 97 % of the energy of tilt-removed PSFs at D/r0 ≥ 1
        lam_px = max(p.wavelengths) / (p.aperture_m * p.ifov_rad)
        half = max(2, math.ceil((2.5 * float(dr0.max()) + 3) * lam_px))
        psfs = self.pupil_for(half).psfs(coeffs, half)  # (Cw, N, w, w)
        bases, weights = [], []
        for ch_psfs in psfs:
            basis, wts = pca_basis(ch_psfs)
            bases.append(basis)
            weights.append(wts)
        k = max(bs.shape[0] for bs in bases)
        basis = torch.stack([F.pad(bs, (0, 0, 0, 0, 0, k - bs.shape[0])) for bs in bases]).to(image)
        wts = torch.stack([F.pad(wt, (0, k - 1 - wt.shape[1])) for wt in weights])  # (Cw, N, K)
        wts = wts.view(len(bases), b, gh, gw, k - 1).permute(1, 0, 4, 2, 3)  # (B, Cw, K, gh, gw)
        if k > 1:
            wts = F.interpolate(wts.reshape(b, -1, gh, gw), size=(h, w), mode="bilinear", align_corners=True)
        wts = wts.reshape(b, len(bases), k - 1, h, w).to(image)

        blurred_k = blur_with_basis(image, basis, wts)
        blurred = modulation * blurred_k + (1 - modulation) * image  # Eq. 4
        fwd_flow_px = (modulation * fwd_flow0_px).to(image.dtype)  # Eq. 5
        turb = warp(blurred, fwd_flow_px).clamp(0, 1)  # Eq. 6
        tilt = warp(image, fwd_flow_px)  # Eq. 7
        return SimResult(
            turb=turb,
            tilt=tilt,
            clean=image,
            fwd_flow_px=fwd_flow_px,
            modulation=modulation,
            dr0=dr0.float().to(self.device),
            blur=blurred,
        )

    # sim.sequence(image, frames, fps, wind, wind_dir, boil, depth, dr0, generator): physically correlated frames,
    # frozen-flow layers moved by the wind; one definition, d2turb.sim.sequence.simulate_sequence (self is its sim)
    sequence = simulate_sequence

    def _check_depth(self, depth, b, h, w):
        if depth is None:
            return None
        if not isinstance(depth, torch.Tensor):
            raise D2TurbError(f"depth must be a tensor (B, 1, H, W), got {type(depth).__name__}")
        if depth.ndim == 2:
            depth = depth[None, None]
        elif depth.ndim == 3:
            depth = depth[None] if depth.shape[0] == 1 else depth[:, None]
        check_shape(depth, f"{1 if depth.shape[:1] == (1,) else b} 1 {h} {w}", "depth")  # one map for all, or one each
        return depth.to(self.device, torch.float32).expand(b, 1, h, w)


def simulate(
    image: torch.Tensor,
    params: TurbulenceParams | None = None,
    depth=None,
    dr0=None,
    seed: int | None = None,
    device=None,
) -> SimResult:
    """One-shot convenience: ``Simulator(params)(image, depth, dr0, generator seeded with seed)``."""
    device = device or (image.device if isinstance(image, torch.Tensor) else "cpu")
    gen = torch.Generator().manual_seed(int(seed)) if seed is not None else None
    return Simulator(params, device)(image, depth=depth, dr0=dr0, generator=gen)
