"""What a person sees in a restored frame, measured against the input frame it came from (``evaluate --real-clips``;
docs/clips.md, "Real clips report"): crushed shadows and clipped highlights, the codec's block grid, noise in flat
regions, edge sharpness, and ghosts (doubled edges) where the camera shook.

Every measure works on the BT.601 luma of a frame in [0, 1] ((3,H,W) tensor or (H,W[,C]) array) and has a map
(``*_map``) whose window sums (:func:`worst_window`) find the region where a restored frame is worst, for the
report's crops.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from d2turb.clip.registration import LUMA_BT601, global_shift_px, to_hwc

NEAR_BLACK_U8 = 4  # luma at or below 4/255 (8-bit, rounded): crushed shadows
NEAR_WHITE_U8 = 251  # luma at or above 251/255: clipped highlights
BLOCK_PX = 8  # the transform block of JPEG and of most video codecs' grids
NOISE_BLOCK_PX = 16  # blocks ranked by flatness for the noise estimate
NOISE_SHARE = 0.1  # the flattest share of those blocks
FLAT_TAIL_MARGIN_U8 = 4  # flat blocks: mean luma in [8, 247] grey levels (noise is not clipped away there)
FLAT_SMOOTH_PX = 2.0  # Gaussian σ before the flatness gradient (its low band: nearly blind to the noise band)
EDGE_SHARE = 0.02  # the reference's strongest edges: this share of its pixels, by gradient magnitude
EDGE_REACH_PX = 2  # the measured frame's peak gradient is looked for within this many px (turbulence moves edges)
GHOST_TOLERANCE_PX = 3  # an output edge within this distance of an input edge is the same edge
GHOST_LEVEL = 0.25  # output edges: gradient above this share of the input's strong-edge gradient
GHOST_PRESENCE = 0.5  # input edges: above GHOST_PRESENCE × GHOST_LEVEL of it (a blurred input edge still counts)
GHOST_SMOOTH_PX = 1.0  # Gaussian σ before the ghost check's gradients (noise is not an edge)
GHOST_EXCESS_MAX = 0.05  # a shaken frame's ghost share above the calm frames' by more than this: a ghost
# Immerkær's mask: the difference of two Laplacians, blind to a plane and (mostly) to image structure
_IMMERKAER = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float32)


def luma(image) -> np.ndarray:
    """BT.601 luma of an image in [0, 1] (one channel: itself).

    Args:
        image: (C,H,W) tensor or (H,W[,C]) array in [0, 1] (uint8: 0–255).

    Returns:
        (H,W) float32 luma in [0, 1] (not clipped).
    """
    hwc = to_hwc(image)
    if hwc.shape[2] < 3:
        return np.ascontiguousarray(hwc[..., 0])
    return np.ascontiguousarray(hwc[..., :3] @ LUMA_BT601)


def _u8(y: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(y * 255), 0, 255).astype(np.uint8)


# ---- crushed shadows, clipped highlights ---------------------------------------------------------------------------
def tail_map(image) -> np.ndarray:
    """Where the luma is near black or near white: (H,W) int8, -1 near black (≤ ``NEAR_BLACK_U8``/255), +1 near
    white (≥ ``NEAR_WHITE_U8``/255), 0 elsewhere (luma rounded to 8 bits, as the frame is shown)."""
    y = _u8(luma(image))
    return (y >= NEAR_WHITE_U8).astype(np.int8) - (y <= NEAR_BLACK_U8).astype(np.int8)


def tail_fractions(image) -> tuple[float, float]:
    """Share of near-black and near-white pixels.

    Args:
        image: (C,H,W) tensor or (H,W[,C]) array in [0, 1].

    Returns:
        (share with luma ≤ 4/255, share with luma ≥ 251/255), in [0, 1], luma rounded to 8 bits.
    """
    t = tail_map(image)
    return float((t < 0).mean()), float((t > 0).mean())


# ---- the codec's block grid ----------------------------------------------------------------------------------------
def _boundary_and_activity(d: np.ndarray, block: int) -> tuple[float, float]:
    """Wang, Sheikh & Bovik's B and A along rows of ``d`` = x(m, n+1) - x(m, n) (0-based columns n = 0..N-2)."""
    n = d.shape[1] + 1  # N columns of the image
    a = np.abs(d)
    boundary = a[:, block - 1 : block * (n // block - 1) : block]  # d(m, 8j), j = 1..⌊N/8⌋-1 (1-based)
    b = float(boundary.mean())
    activity = (block * float(a.mean()) - b) / (block - 1)
    return b, activity


def block_energy(image, block: int = BLOCK_PX) -> float:
    """Codec block-grid energy: the mean |luma difference| across the ``block``-px grid's boundaries over the mean
    within blocks, B / A of Wang, Sheikh & Bovik (ICIP 2002, "No-reference perceptual quality assessment of JPEG
    compressed images", eqs. 1–4): with d_h(m,n) = x(m,n+1) - x(m,n),
    B_h = 1/(M(⌊N/8⌋-1)) Σ_m Σ_j |d_h(m, 8j)|,  A_h = 1/7 [8/(M(N-1)) Σ_m Σ_n |d_h(m,n)| - B_h],
    the same down the columns, B = (B_h + B_v)/2, A = (A_h + A_v)/2. The grid is the frame's own (boundaries after
    every 8th column and row from the top left), where JPEG and video codecs put it. About 1 without a grid, above
    1 with one.

    Args:
        image: (C,H,W) tensor or (H,W[,C]) array in [0, 1], at least 2 ``block`` px each way.

    Returns:
        B / A (NaN for a flat image, A = 0).

    Shape:
        image: H, W ≥ 2 * block.
    """
    y = luma(image).astype(np.float64)
    if min(y.shape) < 2 * block:
        raise ValueError(f"block_energy needs at least {2 * block} px each way, got {y.shape}")
    bh, ah = _boundary_and_activity(np.diff(y, axis=1), block)
    bv, av = _boundary_and_activity(np.diff(y, axis=0).T, block)
    a = (ah + av) / 2
    return (bh + bv) / 2 / a if a > 0 else math.nan


def block_map(image, block: int = BLOCK_PX) -> np.ndarray:
    """Per pixel, its share of B - A of :func:`block_energy`: |difference| to the next column (row) counted +1 at a
    grid boundary and -1/7 inside a block, summed over both axes → (H,W) float32; its window sums are how much the
    grid stands out there (0 on average without one)."""
    y = luma(image)
    out = np.zeros_like(y)
    weight = np.full(block, -1.0 / (block - 1), np.float32)
    weight[block - 1] = 1.0
    dh = np.abs(np.diff(y, axis=1))
    out[:, :-1] += dh * np.resize(weight, dh.shape[1])[None]
    dv = np.abs(np.diff(y, axis=0))
    out[:-1] += dv * np.resize(weight, dv.shape[0])[:, None]
    return out


# ---- noise in flat regions -----------------------------------------------------------------------------------------
def _highpass(y: np.ndarray) -> np.ndarray:
    """|y * Immerkær's mask| / 6 (for white noise of σ: E = σ √(2/π)), 0 on the 1-px border."""
    h = np.abs(cv2.filter2D(y, cv2.CV_32F, _IMMERKAER, borderType=cv2.BORDER_REFLECT)) / 6
    h[0], h[-1], h[:, 0], h[:, -1] = 0, 0, 0, 0
    return h


def flat_mask(reference, block: int = NOISE_BLOCK_PX, share: float = NOISE_SHARE) -> np.ndarray:
    """The flattest ``share`` of the ``block``² blocks of ``reference``, by mean gradient magnitude of its luma
    smoothed by a Gaussian of ``FLAT_SMOOTH_PX`` (the low band, so that the noise band measured in them barely
    sways the choice), among the blocks whose mean luma is at least ``FLAT_TAIL_MARGIN_U8`` grey levels inside the
    near-black and near-white tails (clipped black or white hides noise; all blocks when none is) → (H,W) bool (the
    partial blocks at the right and bottom edges are never chosen).

    Shape:
        reference: H, W ≥ ``block``.
    """
    y = luma(reference)
    s = cv2.GaussianBlur(y, (0, 0), FLAT_SMOOTH_PX)
    g = np.hypot(cv2.Sobel(s, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(s, cv2.CV_32F, 0, 1, ksize=3))
    nby, nbx = y.shape[0] // block, y.shape[1] // block
    if nby < 1 or nbx < 1:
        raise ValueError(f"flat_mask needs at least {block} px each way, got {y.shape}")
    per_block = g[: nby * block, : nbx * block].reshape(nby, block, nbx, block).mean(axis=(1, 3)).ravel()
    level = 255 * y[: nby * block, : nbx * block].reshape(nby, block, nbx, block).mean(axis=(1, 3)).ravel()
    lo, hi = NEAR_BLACK_U8 + FLAT_TAIL_MARGIN_U8, NEAR_WHITE_U8 - FLAT_TAIL_MARGIN_U8
    candidates = np.flatnonzero((level >= lo) & (level <= hi))
    if candidates.size == 0:
        candidates = np.arange(per_block.size)
    keep = max(1, round(share * candidates.size))
    chosen = np.zeros(per_block.size, bool)
    chosen[candidates[np.argsort(per_block[candidates], kind="stable")[:keep]]] = True
    mask = np.zeros(y.shape, bool)
    mask[: nby * block, : nbx * block] = np.kron(chosen.reshape(nby, nbx), np.ones((block, block), bool))
    return mask


def flat_noise_sigma(image, reference=None, block: int = NOISE_BLOCK_PX, share: float = NOISE_SHARE) -> float:
    """Noise in flat regions: Immerkær's fast noise estimate (CVIU 64(2), 1996: σ = √(π/2) / (6 n) Σ |I * N| with
    N = [[1,-2,1],[-2,4,-2],[1,-2,1]]) over the flattest blocks of ``reference`` (:func:`flat_mask`).

    Args:
        image: the frame measured, (C,H,W) tensor or (H,W[,C]) array in [0, 1].
        reference: the frame whose flat blocks are used (None: ``image``); the same size. The report uses the input
            frame, so that every method is measured in the same places.
        block, share: blocks of ``block``² px; the flattest ``share`` of them.

    Returns:
        σ of the luma, in units of the full range (×255: grey levels).
    """
    y = luma(image)
    mask = flat_mask(y if reference is None else reference, block, share)
    mask[0], mask[-1], mask[:, 0], mask[:, -1] = False, False, False, False
    return float(math.sqrt(math.pi / 2) * _highpass(y)[mask].mean())


def noise_map(image, reference=None, block: int = NOISE_BLOCK_PX, share: float = NOISE_SHARE) -> np.ndarray:
    """|Immerkær's high-pass| / 6 of ``image``'s luma inside ``reference``'s flat blocks, 0 elsewhere → (H,W)
    float32 (its mean over the mask × √(π/2) is :func:`flat_noise_sigma`)."""
    y = luma(image)
    return _highpass(y) * flat_mask(y if reference is None else reference, block, share)


# ---- edge sharpness ------------------------------------------------------------------------------------------------
def _gradient(y: np.ndarray, smooth_px: float = 0.0) -> np.ndarray:
    """|∇y| per px (Sobel / 8: a central difference smoothed across), after a Gaussian of ``smooth_px``."""
    if smooth_px > 0:
        y = cv2.GaussianBlur(y, (0, 0), smooth_px)
    return np.hypot(cv2.Sobel(y, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(y, cv2.CV_32F, 0, 1, ksize=3)) / 8


def strong_edges(reference, share: float = EDGE_SHARE) -> np.ndarray:
    """The ``share`` of ``reference``'s pixels with the largest luma gradient, its 2-px border left out → (H,W)
    bool."""
    g = _gradient(luma(reference))
    b = EDGE_REACH_PX + 1
    inner = g[b:-b, b:-b]
    if inner.size == 0:
        raise ValueError(f"strong_edges needs more than {2 * b} px each way, got {g.shape}")
    threshold = np.quantile(inner, 1 - share)
    mask = np.zeros(g.shape, bool)
    mask[b:-b, b:-b] = (inner >= threshold) & (inner > 0)
    return mask


def _peak_gradient(y: np.ndarray) -> np.ndarray:
    """The largest |∇y| within ``EDGE_REACH_PX`` of each pixel."""
    k = 2 * EDGE_REACH_PX + 1
    return cv2.dilate(_gradient(y), np.ones((k, k), np.uint8))


def edge_sharpness(image, reference=None, share: float = EDGE_SHARE) -> float:
    """Edge sharpness: the mean over ``reference``'s strongest edges (:func:`strong_edges`) of ``image``'s largest
    luma gradient within ``EDGE_REACH_PX`` px (so that an edge moved a pixel or two by turbulence is still found),
    ``image`` first moved onto ``reference`` by their global translation rounded to whole pixels (a restored frame of
    a shaken clip sits at its window's pose, up to ~10 px from the hand-shaken input frame's; a whole-pixel move
    copies values, it blurs nothing), the edges the move uncovers left out.
    An ideal step of height A blurred by a Gaussian of σ px peaks at A / (σ √(2π)) per px: the figure falls as 1/σ.

    Args:
        image: the frame measured, (C,H,W) tensor or (H,W[,C]) array in [0, 1].
        reference: whose edges (None: ``image``'s own); the same size. The report uses the input frame.

    Returns:
        Mean peak gradient, luma (full range 1) per px; NaN when the reference has no edge.
    """
    mask = strong_edges(image if reference is None else reference, share)
    y = luma(image)
    if reference is not None:
        r = luma(reference)
        dx, dy = (round(v) for v in global_shift_px(_u8(r), _u8(y)))
        b = max(abs(dx), abs(dy)) + EDGE_REACH_PX
        if (dx or dy) and 2 * b < min(y.shape):  # y(x + (dx, dy)) ≈ reference(x); integer: an exact copy
            m = np.float32([[1, 0, dx], [0, 1, dy]])
            flags = cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
            moved = cv2.warpAffine(y, m, y.shape[::-1], flags=flags, borderMode=cv2.BORDER_REPLICATE)
            inner = (slice(b, -b), slice(b, -b))
            if np.abs(moved - r)[inner].mean() < np.abs(y - r)[inner].mean():  # a true match, not a correlation's alias
                y, mask = moved, mask.copy()
                mask[:b], mask[-b:], mask[:, :b], mask[:, -b:] = False, False, False, False
    if not mask.any():
        return math.nan
    return float(_peak_gradient(y)[mask].mean())


def sharpness_loss_map(image, reference, share: float = EDGE_SHARE) -> np.ndarray:
    """How much sharper ``reference`` is than ``image`` at ``reference``'s strongest edges: their peak gradients'
    difference there (negative where ``image`` is sharper), 0 off those edges → (H,W) float32; its window sums are
    the sharpness lost there."""
    mask = strong_edges(reference, share)
    loss = _peak_gradient(luma(reference)) - _peak_gradient(luma(image))
    return np.where(mask, loss, 0).astype(np.float32)


# ---- ghosts: doubled edges -----------------------------------------------------------------------------------------
def align_to(image, reference, max_side: int = 1024) -> tuple[np.ndarray, np.ndarray, tuple[float, float], int]:
    """``image``'s luma moved onto ``reference``'s by their global translation (phase correlation,
    :func:`~d2turb.clip.registration.global_shift_px`): a restored frame may sit a few px off its input frame as a
    whole (the output's pose), which is not a ghost.

    Returns:
        (aligned luma, reference luma, (dx, dy) px with image(x + (dx, dy)) ≈ reference(x), the border in px that
        the move leaves without content).
    """
    y, r = luma(image), luma(reference)
    dx, dy = global_shift_px(_u8(r), _u8(y), max_side=max_side)
    m = np.float32([[1, 0, dx], [0, 1, dy]])
    aligned = cv2.warpAffine(
        y, m, y.shape[::-1], flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE
    )
    return aligned, r, (dx, dy), math.ceil(max(abs(dx), abs(dy)))


def ghost_map(image, reference, tolerance_px: int = GHOST_TOLERANCE_PX) -> np.ndarray:
    """The edges of ``image`` that ``reference`` lacks: after a global alignment (:func:`align_to`), the gradient of
    ``image`` (smoothed by ``GHOST_SMOOTH_PX``) where it exceeds ``GHOST_LEVEL`` × the reference's strong-edge
    gradient (mean over :func:`strong_edges`) and no reference edge (gradient above ``GHOST_PRESENCE`` × that
    level) lies within ``tolerance_px``; 0 elsewhere → (H,W) float32, in the reference's coordinates.

    A ghost is a copy of an edge displaced by the camera's shake (a frame fused at the wrong pose): an edge of the
    output that is not in the input frame at that pose. The input's threshold is half the output's, so that an input
    edge blurred to half its gradient still counts as present; turbulence moves edges by less than
    ``tolerance_px``.
    """
    return _ghost(image, reference, tolerance_px)[0]


def _ghost(image, reference, tolerance_px: int) -> tuple[np.ndarray, np.ndarray]:
    aligned, r, _, border = align_to(image, reference)
    g_out, g_ref = _gradient(aligned, GHOST_SMOOTH_PX), _gradient(r, GHOST_SMOOTH_PX)
    valid = np.zeros(r.shape, bool)
    b = border + 3
    valid[b:-b, b:-b] = True
    strong = strong_edges(r)
    scale = float(g_ref[strong].mean()) if strong.any() else 0.0
    if scale <= 0:
        zero = np.zeros(r.shape, np.float32)
        return zero, zero
    out_edges = (g_out > GHOST_LEVEL * scale) & valid
    k = 2 * tolerance_px + 1
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    near_ref = cv2.dilate((g_ref > GHOST_PRESENCE * GHOST_LEVEL * scale).astype(np.uint8), disk) > 0
    edges = np.where(out_edges, g_out, 0).astype(np.float32)
    return np.where(near_ref, 0, edges).astype(np.float32), edges


def ghost_share(image, reference, tolerance_px: int = GHOST_TOLERANCE_PX) -> float:
    """Share of ``image``'s edge strength that ``reference`` lacks (:func:`ghost_map` over all of ``image``'s edges
    above the same level): 0 when every edge of the output is an edge of the input frame, about 0.5 for a 50/50
    double exposure of shifted copies (every edge doubled). Deblurring also lifts fine texture over the level, so the
    report compares the shaken frames' share with the calm frames' (``GHOST_EXCESS_MAX``).

    Args:
        image: the restored frame, (C,H,W) tensor or (H,W[,C]) array in [0, 1].
        reference: its input frame, the same size.
        tolerance_px: an output edge this close to an input edge is that edge.

    Returns:
        The share in [0, 1]; NaN when the output has no edge above the level.
    """
    ghost, edges = _ghost(image, reference, tolerance_px)
    total = float(edges.sum())
    return float(ghost.sum()) / total if total > 0 else math.nan


# ---- the worst region ----------------------------------------------------------------------------------------------
def window_sums(values: np.ndarray, side: int, step: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sums of ``values`` over ``side``² windows on a ``step``-px grid (an integral image) → (sums, ys, xs)."""
    h, w = values.shape
    ii = cv2.integral(values.astype(np.float64))
    ys, xs = np.arange(0, h - side + 1, step), np.arange(0, w - side + 1, step)
    sums = ii[ys[:, None] + side, xs[None] + side] - ii[ys[:, None], xs[None] + side]
    sums = sums - ii[ys[:, None] + side, xs[None]] + ii[ys[:, None], xs[None]]
    return sums, ys, xs


def worst_window(badness: np.ndarray, side: int, step: int = 8) -> tuple[int, int]:
    """(y, x) of the ``side``² window (on a ``step``-px grid) with the largest sum of ``badness`` (H,W)."""
    sums, ys, xs = window_sums(badness, side, step)
    iy, ix = np.unravel_index(int(np.argmax(sums)), sums.shape)
    return int(ys[iy]), int(xs[ix])
