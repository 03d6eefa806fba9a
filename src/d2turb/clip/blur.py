"""Blind blur estimate of an image (the fused frame of a clip) and a Wiener deblur with it that does not ring
(docs/clips.md, "the blind deblur, rounds 1 and 2").

Blur model: the image is a sharp scene convolved with a Gaussian of σ px (the turbulence's short-exposure blur,
the residual misregistration the fusion averaged, the optics). At an ideal step edge of height A blurred to σ the
gradient peak is A/(√(2π)·σ); blurred again by a Gaussian of σ0 it is A/(√(2π)·√(σ² + σ0²)), so the ratio of the
two peaks, R = √(σ² + σ0²)/σ, gives σ = σ0/√(R² − 1) without knowing A (Zhuo & Sim, "Defocus map estimation from
a single image", Pattern Recognition 44(9), 2011). The ratio is read at the strongest edges of the image (Canny,
local gradient maxima); the discrete gradient and the pixel grid bias the formula, so R is mapped to σ by a table
made on synthetic step edges of known σ (:func:`ratio_table`). Natural scenes' edges are not ideal steps: the
estimate on sharp images is ``SCENE_SIGMA_PX`` (median over the clean validation images), removed in quadrature,
σ_blur = √(σ_edge² − σ_scene²). Per tile a median; the estimate is the median of the tiles, its spread (median
absolute deviation of ln σ over the tiles) and the number of tiles give the confidence.

Deblur: a Wiener filter with the Gaussian OTF exp(−2π²σ_d²|f|²), σ_d = ``DEBLUR_SHARE``·σ_blur (under-correcting
is safe, over-correcting rings), and the Laplacian smoothness prior of ``clip.deblur``. Ringing guard: the share of
the change that overshoots the fused frame's local range (:func:`ringing_index`, halos and bands do; a correct
deblur of a blurred edge barely does); above ``RINGING_MAX`` σ_d is reduced until it passes, or no deblur.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import cv2
import numpy as np
import torch

from d2turb.clip.deblur import PhysicsDeblur, wiener_deconvolve, wiener_gain, wiener_padding
from d2turb.errors import D2TurbError
from d2turb.sim.otf import image_otf, pixel_frequency_grid

REBLUR_SIGMA_PX = 1.5  # σ0 of the re-blur: larger keeps R away from 1 for wide blurs, smaller resolves narrow ones
TILE_PX = 128  # tiles of the estimate (their spread is its uncertainty)
MIN_EDGES_PER_TILE = 40  # edge pixels for a tile's median
MIN_TILES = 3  # fewer usable tiles: not confident
EDGE_QUANTILE = 0.90  # edge pixels: Canny edges whose gradient is above this quantile of the image's gradient
EDGE_NOISE_FACTOR = 6.0  # ... and above this many noise σ (|∇| of Sobel/8 on white noise of σ is ~0.6σ, rarely 2σ)
# edge width of sharp scenes: the estimate is 0 on all 23 clean set14/mcmaster images tried (their strongest edges are
# as steep as the table's sharpest step), so nothing is removed; kept as the model's parameter
SCENE_SIGMA_PX = 0.0
MAX_SIGMA_PX = 5.0  # about the table's range (5.04 px); wider is not trusted
SPREAD_MAX = 0.35  # MAD of ln σ over the tiles above which the estimate is not confident
MIN_DEBLUR_SIGMA_PX = 0.35  # below: the image is as sharp as a sharp scene, nothing to deblur
# σ_d = DEBLUR_SHARE · σ_blur and the prior weight: on 36 simulated validation clips (set14/mcmaster crops,
# λ/(D·ifov) 1–5 px, D/r0 1.1–4.6, window 16), PSNR with the global offset removed, the largest share whose worst
# clip stays within 0.3 dB of no deblur: +0.68 dB mean over the fusion, worst −0.21 (share 1: +1.05 / +1.30 mean at
# weight 0.01 / 0.002 but 3 / 1 clips below −0.3 dB and a ripple along the airport clip's edges; the physics deblur
# at the true optics +2.35; docs/clips.md)
DEBLUR_SHARE = 0.8
DEBLUR_BALANCE = 0.01
# ringing_index above which the deblur is weakened: above the largest value of the chosen deblur on the validation
# clips (0.60; median 0.43); a deblur at twice the estimated σ reaches 0.55–0.75 there
RINGING_MAX = 0.65
RINGING_STEPS = (1.0, 0.75, 0.5)  # factors on σ_d tried in turn by the guard

# The physics-shaped deblur (the default shape): the turbulence OTF family of ``sim.otf`` at an assumed D/r0 =
# ``PHYSICS_DR0``, its λ/(D·ifov) chosen so that the edge estimate of that OTF's blur (``compute_physics_response``,
# on the synthetic step edges of the ratio table) equals ``PHYSICS_SHARE``·σ_blur, and the Wiener filter of the
# physics deblur (``clip.deblur.PhysicsDeblur``) with a Laplacian prior weighing ``PHYSICS_BALANCE``, gain ≥ 1.
# Calibration against the simulator's known blur: the fused frame's edge estimate is 1.00× (median; 10–90 %:
# 0.73–1.18×) the estimate of its true OTF on the step edges on 39 validation clips, 0.74× (0.53–0.92×) on the 15
# fixed test clips, 0.70–1.16× on skimage scenes (tests/test_clip_blind.py): no bias correction. Grid (docs/clips.md:
# D/r0 1, 2, 3 × share 0.7–1.5 × weight 0.0006–0.02, PSNR with the global offset removed): D/r0 1; share 1 kept the
# most on the clean simulated clips (49/49/37 % of the oracle's gain per bin) but lost 1.2 dB on a clip of the blind
# test set (noise, JPEG: its estimate 1.8× the response), share 0.8 keeps 47/46/36 % (validation), 22/39/58 %
# (fixed test), 49/72/101 % (blind set), no clip below −0.25 dB; the weight 0.02 (not D/r0 1's 0.0006, which gained
# more on clean clips) because smaller weights turn the real clips' compression blocks into a visible grid.
PHYSICS_DR0 = 1.0
PHYSICS_SHARE = 0.8
PHYSICS_BALANCE = 0.02
# above this edge estimate the Gaussian at DEBLUR_SHARE·σ is used instead: the estimates of 2.9–3.5 px came from
# strong turbulence where the oracle itself gains little (+0.5 dB) or loses, and the physics shape lost up to 0.7 dB
PHYSICS_MAX_SIGMA_PX = 2.8
# ringing guard of the physics shape: above the largest ringing_index of the deblur at share 1 on the validation and
# test clips (0.66; median 0.61 / 0.50); 0.70 stops a deblur that overshoots more than any that paid there
PHYSICS_RINGING_MAX = 0.70


def _luma(image) -> np.ndarray:
    """(H, W) float32 luma in [0, 1] of a (3,H,W)/(1,H,W) tensor or an (H,W[,C]) array."""
    if isinstance(image, torch.Tensor):
        arr = image.detach().cpu().float().numpy()
        arr = arr[0] if arr.shape[0] == 1 else np.tensordot(np.array([0.299, 0.587, 0.114], np.float32), arr[:3], 1)
    else:
        arr = np.asarray(image, np.float32)
        if arr.ndim == 3:
            arr = arr[..., 0] if arr.shape[2] == 1 else arr[..., :3] @ np.array([0.299, 0.587, 0.114], np.float32)
    if arr.ndim != 2:
        raise D2TurbError(f"expected an image, got shape {arr.shape}")
    return np.ascontiguousarray(arr, dtype=np.float32)


def _grad_mag(g: np.ndarray) -> np.ndarray:
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8
    return np.sqrt(gx * gx + gy * gy)


def noise_sigma(g: np.ndarray) -> float:
    """Standard deviation of white noise in a grey image (Immerkær, "Fast noise variance estimation", CVIU 64(2),
    1996): σ = √(π/2)·mean|g ⊛ N|/6 with N = [[1,−2,1],[−2,4,−2],[1,−2,1]] (blind to ramps; texture raises it)."""
    kernel = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    r = cv2.filter2D(g, cv2.CV_32F, kernel)[1:-1, 1:-1]
    return math.sqrt(math.pi / 2) * float(np.abs(r).mean()) / 6


def _ratios(g: np.ndarray, quantile: float = EDGE_QUANTILE) -> tuple[np.ndarray, np.ndarray]:
    """Gradient-peak ratios R = |∇g| / |∇(g ⊛ G_σ0)| at the image's strong edge pixels, and their (y, x)."""
    mag = _grad_mag(g)
    mag0 = _grad_mag(cv2.GaussianBlur(g, (0, 0), REBLUR_SIGMA_PX, borderType=cv2.BORDER_REFLECT))
    u8 = np.clip(g * 255 + 0.5, 0, 255).astype(np.uint8)
    hi = float(np.quantile(mag, quantile)) * 255 * 8  # cv2.Canny's L1-free Sobel scale
    edges = cv2.Canny(u8, max(hi * 0.5, 1.0), max(hi, 2.0), L2gradient=True) > 0
    m = 6  # no borders (the filters' reflection)
    edges[:m], edges[-m:], edges[:, :m], edges[:, -m:] = False, False, False, False
    edges &= mag >= max(float(np.quantile(mag, quantile)), EDGE_NOISE_FACTOR * noise_sigma(g))
    ys, xs = np.nonzero(edges)
    r = mag[ys, xs] / np.maximum(mag0[ys, xs], 1e-6)
    return r, np.stack([ys, xs], 1)


# (R, σ) of compute_ratio_table(), rounded (tests/test_clip_blind.py recomputes it): beyond σ ≈ 5 px the disc's
# curvature breaks the step-edge model, so the table stops at 5.04 px
RATIO_TABLE_R = (
    2.1014, 2.0780, 2.0723, 2.0649, 2.0539, 2.0423, 2.0287, 2.0114, 1.9911, 1.9681, 1.9421, 1.9144, 1.8826,
    1.8484, 1.8107, 1.7697, 1.7258, 1.6787, 1.6309, 1.5813, 1.5317, 1.4827, 1.4352, 1.3896, 1.3466, 1.3064,
    1.2694, 1.2356, 1.2050, 1.1777, 1.1534, 1.1319, 1.1129, 1.0967, 1.0823, 1.0701, 1.0595, 1.0502, 1.0411,
)  # fmt: skip
RATIO_TABLE_SIGMA = (
    0.0000, 0.2000, 0.2182, 0.2381, 0.2598, 0.2835, 0.3093, 0.3375, 0.3683, 0.4018, 0.4384, 0.4784, 0.5220,
    0.5695, 0.6214, 0.6781, 0.7399, 0.8073, 0.8809, 0.9611, 1.0487, 1.1443, 1.2485, 1.3623, 1.4865, 1.6219,
    1.7697, 1.9310, 2.1069, 2.2989, 2.5084, 2.7370, 2.9864, 3.2586, 3.5555, 3.8795, 4.2330, 4.6188, 5.0397,
)  # fmt: skip


# (λ/(D·ifov), σ) of compute_physics_response() at PHYSICS_DR0, rounded (tests/test_clip_blind.py recomputes it)
PHYSICS_RESPONSE_LOD = (
    0.2500, 0.2805, 0.3148, 0.3533, 0.3965, 0.4449, 0.4993, 0.5603, 0.6287, 0.7055, 0.7917, 0.8885, 0.9970,
    1.1189, 1.2556, 1.4090, 1.5811, 1.7743, 1.9911, 2.2344, 2.5074, 2.8138, 3.1576, 3.5434, 3.9764, 4.4622,
    5.0074, 5.6192, 6.3058, 7.0763, 7.9409, 8.9112, 10.0000,
)  # fmt: skip
PHYSICS_RESPONSE_SIGMA = (
    0.2954, 0.3104, 0.3263, 0.3444, 0.3627, 0.3830, 0.4059, 0.4309, 0.4595, 0.4907, 0.5250, 0.5619, 0.6023,
    0.6470, 0.6948, 0.7484, 0.8080, 0.8778, 0.9553, 1.0461, 1.1531, 1.2800, 1.4254, 1.5910, 1.7790, 1.9968,
    2.2399, 2.5096, 2.8229, 3.1687, 3.5495, 3.9984, 4.4763,
)  # fmt: skip


def compute_ratio_table(count: int = 41) -> tuple[np.ndarray, np.ndarray]:
    """(R, σ): the median gradient-peak ratio of synthetic step edges (all orientations, sub-pixel positions: a
    disc of radius 40 px super-sampled 8×, area-averaged to pixels) blurred by a Gaussian of known σ (0, then
    0.2–6 px geometric); R falls with σ. Takes seconds: ``RATIO_TABLE_*`` hold its values."""
    sigmas = np.concatenate([[0.0], np.geomspace(0.2, 6.0, count - 1)])
    n, sup = 160, 8
    yy, xx = np.mgrid[0 : n * sup, 0 : n * sup].astype(np.float32)
    c = n * sup / 2 - 0.37 * sup
    rad = np.sqrt((xx - c) ** 2 + (yy - c) ** 2)
    disc = (rad < 40 * sup).astype(np.float32)
    ratios = []
    for s in sigmas:
        hi = cv2.GaussianBlur(disc, (0, 0), s * sup) if s > 0 else disc
        img = cv2.resize(hi, (n, n), interpolation=cv2.INTER_AREA)  # pixel integration
        img = 0.2 + 0.6 * img
        r, _ = _ratios(img, 0.0)
        ratios.append(float(np.median(r)) if r.size else 1.0)
    return np.array(ratios), sigmas


def _step_disc(n: int = 160, sup: int = 8) -> np.ndarray:
    """The synthetic step edges of the tables: a disc of radius 40 px (off-centre), super-sampled ``sup``× and
    area-averaged to (n, n) pixels, values 0/1."""
    yy, xx = np.mgrid[0 : n * sup, 0 : n * sup].astype(np.float32)
    c = n * sup / 2 - 0.37 * sup
    disc = ((xx - c) ** 2 + (yy - c) ** 2 < (40 * sup) ** 2).astype(np.float32)
    return cv2.resize(disc, (n, n), interpolation=cv2.INTER_AREA)


def compute_physics_response(dr0: float = PHYSICS_DR0, count: int = 33) -> tuple[np.ndarray, np.ndarray]:
    """(λ/(D·ifov), σ): the edge estimate (median σ over the strongest 3 % of the edge pixels) of the synthetic step
    edges of the ratio table blurred by the short-exposure turbulence OTF (``sim.otf.image_otf``, tilt removed) at
    ``dr0``, for λ/(D·ifov) from 0.25 to 10 px (geometric). ``PHYSICS_RESPONSE_*`` hold its values at PHYSICS_DR0."""
    pad = 64
    img = np.pad(_step_disc(), pad, mode="edge")
    spec = torch.fft.rfft2(torch.from_numpy(img).double())
    lods = np.geomspace(0.25, 10.0, count)
    sig = []
    for lod in lods:
        b = torch.fft.irfft2(spec * image_otf(*img.shape, dr0, float(lod)), s=img.shape).numpy()
        r, _ = _ratios((0.2 + 0.6 * b[pad:-pad, pad:-pad]).astype(np.float32), 0.97)
        sig.append(float(np.median(sigma_from_ratio(r))) if r.size else MAX_SIGMA_PX)
    return lods, np.maximum.accumulate(np.array(sig))


def ratio_table() -> tuple[np.ndarray, np.ndarray]:
    """(R, σ) of the tabulated ``compute_ratio_table``."""
    return np.array(RATIO_TABLE_R), np.array(RATIO_TABLE_SIGMA)


def sigma_from_ratio(r: np.ndarray) -> np.ndarray:
    """σ (px) of the edges' Gaussian blur from their gradient-peak ratios (the table, linear between nodes)."""
    table_r, table_s = ratio_table()
    return np.interp(-np.asarray(r, np.float64), -table_r, table_s)


def physics_lod_for_sigma(sigma_px: float) -> float:
    """λ/(D·ifov) (px) of the turbulence OTF at PHYSICS_DR0 whose edge estimate is ``sigma_px`` (the tabulated
    ``compute_physics_response``, linear between nodes, clamped to its 0.25–10 px)."""
    return float(np.interp(sigma_px, PHYSICS_RESPONSE_SIGMA, PHYSICS_RESPONSE_LOD))


@dataclass
class BlurEstimate:
    """A blind estimate of an image's Gaussian blur: ``sigma_px`` (the blur beyond a sharp scene's edges), its 90 %
    interval from the spread over tiles, ``sigma_low_px`` (the lower quartile of the tiles: a blur that three
    quarters of the image has at least, for a conservative deblur where the blur varies), ``edge_sigma_px``
    (before the scene's own edge width is removed),
    ``tiles`` used, ``spread`` (MAD of ln σ over them), ``confident`` and, when not, ``reason``."""

    sigma_px: float
    sigma_ci: tuple[float, float]
    sigma_low_px: float
    edge_sigma_px: float
    tiles: int
    spread: float
    confident: bool
    reason: str = ""

    def as_dict(self) -> dict:
        return asdict(self)


def estimate_blur(image, tile: int = TILE_PX) -> BlurEstimate:
    """Blind estimate of the Gaussian blur σ (px) of an image from its strongest edges (see the module's doc).

    Args:
        image: (3,H,W) / (1,H,W) tensor or (H,W[,C]) array in [0, 1] (e.g. a clip's fused frame).
        tile: side of the tiles whose medians give the estimate and its spread.
    """
    g = _luma(image)
    h, w = g.shape
    if min(h, w) < 32:
        raise D2TurbError(f"an image of {w}x{h} is too small to estimate its blur (need 32 px per side)")
    r, pos = _ratios(g)
    sig = sigma_from_ratio(r)
    # tiles of about ``tile`` px, at least 3 per side where they stay 32 px or more
    ty, tx = (max(min(3, n // 32), round(n / tile), 1) for n in (h, w))
    key = np.minimum(pos[:, 0] * ty // h, ty - 1) * tx + np.minimum(pos[:, 1] * tx // w, tx - 1)
    medians = []
    for k in range(ty * tx):
        s = sig[key == k]
        if s.size >= MIN_EDGES_PER_TILE:
            medians.append(float(np.median(s)))
    medians = np.array(medians)
    if medians.size == 0:
        return BlurEstimate(0.0, (0.0, 0.0), 0.0, 0.0, 0, math.inf, False, "too few strong edges")
    edge = float(np.median(medians))
    logs = np.log(np.maximum(medians, 0.05))
    spread = float(1.4826 * np.median(np.abs(logs - np.median(logs)))) if medians.size > 1 else math.inf
    blur = math.sqrt(max(edge**2 - SCENE_SIGMA_PX**2, 0.0))
    low = math.sqrt(max(float(np.quantile(medians, 0.25)) ** 2 - SCENE_SIGMA_PX**2, 0.0))
    half = 1.645 * spread / math.sqrt(max(medians.size, 1)) if math.isfinite(spread) else math.inf
    lo_e, hi_e = edge * math.exp(-half) if math.isfinite(half) else 0.0, edge * math.exp(min(half, 5.0))
    ci = tuple(math.sqrt(max(e**2 - SCENE_SIGMA_PX**2, 0.0)) for e in (lo_e, hi_e))
    reason = ""
    if medians.size < MIN_TILES:
        reason = f"strong edges in only {medians.size} tile(s) of {tile} px (need {MIN_TILES})"
    elif spread > SPREAD_MAX:
        reason = f"the blur differs across the image (spread {spread:.2f} in ln σ, limit {SPREAD_MAX:g})"
    elif edge >= 0.95 * MAX_SIGMA_PX:
        reason = f"the edges are wider than the {MAX_SIGMA_PX:g} px the estimate covers"
    return BlurEstimate(blur, ci, low, edge, int(medians.size), spread, not reason, reason)


def gaussian_otf(shape: tuple[int, int], sigma_px: float) -> torch.Tensor:
    """exp(−2π²σ²|f|²) on the rfft2 grid of ``shape`` (float64): the OTF of a Gaussian blur of σ px."""

    return torch.exp(-2 * math.pi**2 * sigma_px**2 * pixel_frequency_grid(*shape) ** 2)


def ringing_index(fused: torch.Tensor, restored: torch.Tensor, radius: int = 2) -> float:
    """Share of the deblur's change that overshoots the fused frame's local range: rms of restored − clip(restored,
    local min, local max of fused over a (2·radius+1)² box) over rms of restored − fused. Halos and dark bands lie
    outside the range; sharpening a blurred edge moves values within it."""
    a, lo, hi = _local_range(fused, radius)
    b = restored.detach().float().cpu().numpy().transpose(1, 2, 0)
    over = b - np.clip(b, lo, hi)
    change = float(np.sqrt(np.mean((b - a) ** 2)))
    return float(np.sqrt(np.mean(over**2))) / change if change > 1e-6 else 0.0


def _local_range(fused: torch.Tensor, radius: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(fused (H,W,C), its local min, its local max over a (2·radius+1)² box), kept on the tensor until it changes
    (``_version``): the ringing guard tries up to six deblurs of one fused frame (1080p: 0.1 s each to make)."""
    key = (radius, fused._version)
    held = getattr(fused, "_d2turb_local_range", None)
    if held is not None and held[0] == key:
        return held[1]
    a = fused.detach().float().cpu().numpy().transpose(1, 2, 0)
    k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    lo, hi = cv2.erode(a, k), cv2.dilate(a, k)
    made = (a, lo.reshape(a.shape), hi.reshape(a.shape))
    try:
        fused._d2turb_local_range = (key, made)
    except (AttributeError, RuntimeError):  # a tensor that takes no attributes: made again next time
        pass
    return made


CODEC_BLOCK_PX = 8  # the transform block of JPEG and of most video codecs' grids
# rise of blockiness_index a deblur may add: above every rise the default deblur made on the 24 validation clips with
# JPEG 75–95 frames (at most 0.10, median 0.02) and on the real clips' sheets of issue 35 (at most 0.20,
# airport_heat_shimmer), below the lattice that the gradient prior's deblur printed on clear_hot_air/test5 (0.24); a
# thin margin on few clips (docs/clips.md, "The Wiener filter's prior")
BLOCK_RISE_MAX = 0.21


def blockiness_index(image: torch.Tensor, block: int = CODEC_BLOCK_PX) -> float:
    """How much a codec's block grid stands out: the mean |difference| of neighbouring columns (rows) at each phase
    modulo ``block``, its largest phase over the median phase, the larger of the two axes; about 1 for an image with
    no grid (the boundary-against-inside idea of Wang, Sheikh & Bovik, ICIP 2002; no maintained library offers a
    blockiness measure). A still camera's codec grid stays in place, so the fusion keeps it, and a deblur that
    amplifies it turns it into a lattice.

    Shape:
        image: (C, H, W); an axis shorter than two blocks shows no grid (1 for an image that small both ways).
    """
    g = image.detach().float().cpu().numpy().mean(0)
    ratios = [1.0]
    for d in (np.abs(np.diff(g, axis=1)), np.abs(np.diff(g, axis=0)).T):
        if d.shape[1] >= 2 * block:
            phase = np.array([d[:, p::block].mean() for p in range(block)])
            ratios.append(float(phase.max() / max(float(np.median(phase)), 1e-12)))
    return max(ratios)


class GaussianDeblur:
    """Wiener deconvolution of a Gaussian blur of ``sigma_px`` with the Laplacian prior (``deblur.prior_power``)."""

    def __init__(self, sigma_px: float, balance: float = DEBLUR_BALANCE):
        if not math.isfinite(sigma_px) or not 0 < sigma_px <= 20:
            raise D2TurbError(f"the deblur's σ must be in (0, 20] px, got {sigma_px!r}")
        self.sigma_px, self.balance = float(sigma_px), float(balance)
        self._gain: dict = {}

    def __call__(self, image: torch.Tensor) -> torch.Tensor:

        size = tuple(image.shape[-2:])
        if size not in self._gain:
            top, bottom, left, right = wiener_padding(*size)
            shape = (size[0] + top + bottom, size[1] + left + right)
            self._gain[size] = wiener_gain(gaussian_otf(shape, self.sigma_px), self.balance, shape, "laplacian")
        return wiener_deconvolve(image, self._gain[size])


def physics_deblur_at(lod: float) -> PhysicsDeblur:
    """``PhysicsDeblur`` at PHYSICS_DR0 and ``lod`` whose Wiener gain never falls below 1 (``boost_only``: a blind
    width that overshoots the true one would otherwise erase detail past its assumed diffraction cut-off, a loss of
    1.2 dB on a weak-turbulence clip of the blind test set)."""
    return PhysicsDeblur(PHYSICS_DR0, lod, balance=PHYSICS_BALANCE, boost_only=True, prior="laplacian")


__all__ = [
    "BlurEstimate",
    "GaussianDeblur",
    "blockiness_index",
    "estimate_blur",
    "gaussian_otf",
    "compute_physics_response",
    "compute_ratio_table",
    "physics_lod_for_sigma",
    "noise_sigma",
    "ratio_table",
    "ringing_index",
    "sigma_from_ratio",
]
