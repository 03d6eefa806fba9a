"""The default deblur of a clip's fused frames, blind (docs/clips.md, "the learned blur estimate"): which filter,
how strong, and the guards that keep it from ringing. The estimates it reads: the learned one of ``clip.blur_net``
(default) and the edge one of ``clip.blur``."""

from __future__ import annotations

import math

import torch

from d2turb.clip.blur import (
    BLOCK_RISE_MAX,
    DEBLUR_SHARE,
    MAX_SIGMA_PX,
    MIN_DEBLUR_SIGMA_PX,
    MIN_TILES,
    PHYSICS_DR0,
    PHYSICS_MAX_SIGMA_PX,
    PHYSICS_RINGING_MAX,
    PHYSICS_SHARE,
    RINGING_MAX,
    RINGING_STEPS,
    SPREAD_MAX,
    GaussianDeblur,
    blockiness_index,
    estimate_blur,
    physics_deblur_at,
    physics_lod_for_sigma,
    ringing_index,
)
from d2turb.clip.blur_net import PATCH_PX, TILT_SPREAD_FLOOR_PX, estimate_blur_params, load_blur_net, tilt_spread
from d2turb.clip.deblur import PhysicsDeblur, fusion_prior, padded_spectra
from d2turb.clip.registration import as_bilinear_mean
from d2turb.device import one_torch_thread
from d2turb.errors import D2TurbError
from d2turb.sim.otf import short_exposure_width, turbulence_otf

SHAPES = ("learned", "physics", "gaussian")
# the learned shape deblurs at λ/(D·ifov)·exp(−LEARNED_SHRINK·sd), sd the network's standard deviation of its ln:
# an uncertain estimate is used weaker (under-correcting is safe, over-correcting rings); chosen on the validation
# clips (docs/clips.md)
LEARNED_SHRINK = 0.25
# the learned shape's deblur models D/r0 at most this: the physics OTF's halo at larger D/r0 is what a fused frame
# matches least (the registration's residual blur and Gaussian-like blurs have none); on the 48 window-16 validation
# clips (first network, no ringing guard) the cap kept 90 / 89 / 100 % of the oracle's gain against 92 / 83 / 101 %
# uncapped, and the worst clip lost 0.93 dB instead of 2.63 (docs/clips.md)
LEARNED_MAX_DR0 = 2.5
# the learned blur's MTF at 0.25 cycles/px (M·T(0.25·λ/(D·ifov); D/r0) + 1 − M) at or above which the frame is
# taken as sharp (nothing to deblur): the sharp samples of the training are taught M 0.1, an MTF of 0.9+
LEARNED_SHARP_MTF = 0.8
# a clip whose registered frames move less than this (rms about the frame's mean, px) shows no turbulence, and so no
# turbulent blur to undo: the blind deblur leaves it alone (DIS reads about 0.02-0.05 px on a still, noisy clip; the
# weakest clip of the blind test set, D/r0 1.08, reads 0.64 px)
STILL_TILT_RMS_PX = 0.15
# ringing guard of the learned shape (ringing_index of the deblur; RINGING_STEPS on λ/(D·ifov))
LEARNED_RINGING_MAX = PHYSICS_RINGING_MAX


class BlindDeblur:
    """The default deblur of a clip's fused frames: the blur is estimated on the first fused frame it is given
    (every later frame is deblurred with the same filter, no flicker). With ``shape`` "learned" (default) the
    network of ``clip.blur_net`` reads the frame and the first window's registered motion (:meth:`observe`) and the
    physics Wiener filter (:class:`PhysicsDeblur`, gain ≥ 1) runs at its D/r0, λ/(D·ifov) (shrunk by its
    uncertainty, ``LEARNED_SHRINK``) and depth modulation; nothing when the learned blur keeps most of the contrast
    (a sharp frame) or the edge estimate (:func:`estimate_blur`) finds too few edges. With "physics" (round 2) the
    physics filter at D/r0 ``PHYSICS_DR0`` and the λ/(D·ifov) whose edge estimate is ``PHYSICS_SHARE``·σ
    (:func:`physics_lod_for_sigma`); with "gaussian"
    (round 1) a :class:`GaussianDeblur` at ``DEBLUR_SHARE``·σ; for these two, where the blur varies across the
    image (tiles' spread above ``SPREAD_MAX``) the Gaussian at ``DEBLUR_SHARE`` of the lower quartile of the tiles
    (conservative), and an unreliable edge estimate deblurs nothing. Every shape is weakened by its ringing guard.
    ``record`` says what was used and why; ``note`` is the one line for the user (empty when the estimate was used
    as is).

    Args:
        shape: "learned" (default), "physics" (round 2: the short-exposure OTF at an assumed D/r0) or "gaussian"
            (round 1).
        weights: the learned shape's network (a ``blur_net`` weights file; default: the shipped one).
        shrink: the learned λ/(D·ifov) is used at exp(−shrink·sd) of itself, sd the network's uncertainty of its ln.
        fusion: the fusion of the frames it deblurs, which sets the learned shape's Wiener prior
            (:func:`~d2turb.clip.deblur.fusion_prior`).

    Returns:
        Called on a fused frame: the deblurred frame (the frame itself when nothing is deblurred).

    Shape:
        (C, H, W) float32 in [0, 1] → (C, H, W) float32 in [0, 1].

    Example:
        >>> deblur = BlindDeblur()
        >>> restorer = ClipRestorer(temporal=16, deblur=deblur)  # doctest: +SKIP
        >>> deblur.record["sigma_px"]  # after the first frame  # doctest: +SKIP
    """

    def __init__(self, shape: str = "learned", weights=None, shrink: float = LEARNED_SHRINK, fusion: str = "mean"):
        if shape not in SHAPES:
            raise D2TurbError(f"the blind deblur's shape must be one of {', '.join(SHAPES)}, got {shape!r}")
        if not math.isfinite(shrink) or shrink < 0:
            raise D2TurbError(f"the learned estimate's shrink must be finite and >= 0, got {shrink!r}")
        self.shape, self.shrink, self.prior = shape, float(shrink), fusion_prior(fusion)
        self.net = load_blur_net(weights) if shape == "learned" and weights is not None else None  # None: shipped
        self.bwd_flow_px = None  # a registered frame's flow of the first window (observe), read by the learned shape
        self.moving = None  # ... and its moving-object share (the flow there is the objects' own)
        self.deblur = None
        self.record: dict | None = None
        self.note = ""

    linear_light = True  # the clip room gives it the fused frame in linear light (clip.deblur.ClipDeblur)

    def observe(self, frame) -> None:
        """Called by ``ClipRestorer`` with each output :class:`ClipFrame` before its deblur: keeps the first frame's
        registered flow (the learned estimate reads its spread)."""
        if self.bwd_flow_px is None:
            self.bwd_flow_px, self.moving = frame.bwd_flow_px, frame.fallback

    def decide(self, fused: torch.Tensor, resampled: str = "bicubic") -> None:
        """Decide the deblur on a fused frame whose registered frames were ``resampled`` "bicubic" (the clip room's:
        read through ``registration.as_bilinear_mean``, the bilinear mean the estimate was made on) or "bilinear"
        (the live preset's, ``clip.live``: read as it is)."""
        if resampled not in ("bicubic", "bilinear"):
            raise D2TurbError(f"resampled must be 'bicubic' or 'bilinear', got {resampled!r}")
        with one_torch_thread():  # a few FFTs and a tiny network, beside the registration (d2turb.device)
            self._decide(as_bilinear_mean(fused) if resampled == "bicubic" else fused)

    def _decide(self, fused: torch.Tensor) -> None:
        est = estimate_blur(fused)
        rec = {
            "method": "blind",
            "estimate": est.as_dict(),
            "sigma_px": 0.0,
            "source": "estimated from the fused frame (edges)",
        }
        if self.shape == "learned" and min(fused.shape[-2:]) >= PATCH_PX:  # smaller: the edge estimate, physics shape
            self._decide_learned(fused, est, rec)
            return
        target = est.sigma_px
        varies = est.tiles >= MIN_TILES and est.spread > SPREAD_MAX and est.edge_sigma_px < 0.95 * MAX_SIGMA_PX
        if not est.confident and varies:
            target = est.sigma_low_px  # the blur varies: deblur only what three quarters of the image has at least
            rec["conservative"] = f"lower quartile of the tiles, {target:.2f} px ({est.reason})"
        physics = self.shape != "gaussian" and "conservative" not in rec and target <= PHYSICS_MAX_SIGMA_PX
        share = PHYSICS_SHARE if physics else DEBLUR_SHARE
        if not est.confident and "conservative" not in rec:
            self.note = f"no deblurring: the blur estimate is not reliable ({est.reason})"
        elif target * share < MIN_DEBLUR_SIGMA_PX:
            if "conservative" in rec:
                self.note = f"no deblurring: {est.reason}, and a quarter of the image or more is sharp"
            else:
                rec["reason"] = f"estimated blur σ {est.sigma_px:.2f} px: as sharp as a sharp scene"
        elif physics:
            rec["shape"] = "physics"
            rec["dr0_assumed"] = PHYSICS_DR0
            sigmas = [x for x in (target * PHYSICS_SHARE * k for k in RINGING_STEPS) if x >= MIN_DEBLUR_SIGMA_PX]
            tries = (
                ({"sigma_px": x, "lambda_over_d_px": lod}, physics_deblur_at(lod))
                for x, lod in ((x, physics_lod_for_sigma(x)) for x in sigmas)
            )
            used = self._guarded(fused, rec, tries, PHYSICS_RINGING_MAX)
            if used:
                rec["sigma_px"], rec["lambda_over_d_px"] = used["sigma_px"], used["lambda_over_d_px"]
            self._guard_note(rec, "sigma_px", target * PHYSICS_SHARE)
        else:
            rec["shape"] = "gaussian"
            sigmas = [x for x in (target * DEBLUR_SHARE * k for k in RINGING_STEPS) if x >= MIN_DEBLUR_SIGMA_PX]
            used = self._guarded(fused, rec, (({"sigma_px": x}, GaussianDeblur(x)) for x in sigmas), RINGING_MAX)
            if used:
                rec["sigma_px"] = used["sigma_px"]
            self._guard_note(rec, "sigma_px", target * DEBLUR_SHARE)
            if self.deblur is not None and "conservative" in rec and not self.note:
                self.note = f"deblurring conservatively at σ {rec['sigma_px']:.2f} px: {est.reason}"
        if self.note:
            rec["note"] = self.note
        self.record = rec

    def _decide_learned(self, fused: torch.Tensor, est, rec: dict) -> None:
        """The physics Wiener filter at the learned estimate (``boost_only``, D/r0 at most ``LEARNED_MAX_DR0``), its
        λ/(D·ifov) shrunk by its uncertainty, weakened by the ringing guard; nothing when the
        learned blur keeps most of the contrast (``LEARNED_SHARP_MTF``), none with a note when the edge estimate
        finds too few edges (a blur that varies across the frame is the depth modulation M the network estimates:
        the edge shapes' lower-quartile rule lost 2–3 dB on 3 of the 48 validation clips)."""
        rec["shape"] = "learned"
        if est.tiles < MIN_TILES:  # too few strong edges: nothing shows the blur, the texture may be noise
            self._no_deblur(rec, f"no deblurring: the blur estimate is not reliable ({est.reason})")
            return
        if self.bwd_flow_px is not None:  # tilt_spread: ln(rms about its rigid motion + 0.05 px), the network's input
            rms = math.exp(tilt_spread(self.bwd_flow_px, self.moving)) - TILT_SPREAD_FLOOR_PX
            rec["tilt_rms_px"] = rms
            if rms < STILL_TILT_RMS_PX:
                rec["reason"] = f"the frames hardly move ({rms:.2f} px rms): no turbulence, nothing to deblur"
                self.record = rec
                return
        b = estimate_blur_params(fused, self.bwd_flow_px, self.net, self.moving)
        rec["learned"] = b.as_dict()
        rec["source"] = "estimated from the fused frame and the registered motion (learned, clip.blur_net)"
        mtf = b.modulation * float(turbulence_otf(torch.tensor([0.25 * b.lambda_over_d_px]), b.dr0)) + 1 - b.modulation
        rec["learned_mtf_quarter"] = mtf
        if mtf >= LEARNED_SHARP_MTF:
            rec["reason"] = f"the learned blur keeps {mtf:.2f} of the contrast at a quarter cycle per px: sharp"
            self.record = rec
            return
        dr0 = min(max(b.dr0, 0.05), LEARNED_MAX_DR0)
        full = min(max(b.lambda_over_d_px * math.exp(-self.shrink * b.log_sd[1]), 0.05), 50.0)
        m = min(max(b.modulation, 1e-3), 1.0)

        def deblur_at(lod: float, prior: str) -> PhysicsDeblur:  # at the prior's default_balance
            return PhysicsDeblur(dr0, max(lod, 0.05), modulation=m, boost_only=True, prior=prior)

        # from the strongest deblur to the weakest; at each strength the fusion's prior, then the Laplacian's stiffer
        # one, which amplifies a codec grid less
        priors = dict.fromkeys((self.prior, "laplacian"))
        tries = (
            ({"lambda_over_d_px": full * k, "prior": p}, deblur_at(full * k, p)) for k in RINGING_STEPS for p in priors
        )
        used = self._guarded(fused, rec, tries, LEARNED_RINGING_MAX)
        if used:
            lod = used["lambda_over_d_px"]
            rec.update(dr0=dr0, lambda_over_d_px=lod, modulation=m, sigma_px=short_exposure_width(dr0) * lod)
            rec["prior"] = used["prior"]
        self._guard_note(rec, "lambda_over_d_px", full)
        if self.note:
            rec["note"] = self.note
        self.record = rec

    def _guarded(self, fused: torch.Tensor, rec: dict, tries, limit: float) -> dict | None:
        """The ringing guard of every shape: ``tries`` yields (entry, deblur) from the full deblur to the weakest;
        each is run on ``fused`` and recorded in ``rec["ringing_tried"]`` with its :func:`ringing_index` and the rise
        of its :func:`blockiness_index`; the first at or under ``limit`` that raises the codec grid by at most
        ``BLOCK_RISE_MAX`` becomes the deblur and its entry is returned (None: every one overshoots)."""
        blocks = spectra = None
        for entry, candidate in tries:
            if isinstance(candidate, PhysicsDeblur):  # the frame's spectra made once for every try
                spectra = padded_spectra(fused) if spectra is None else spectra
                out = candidate(fused, spectra)
            else:
                out = candidate(fused)
            blocks = blockiness_index(fused) if blocks is None else blocks
            entry["ringing_index"] = ringing_index(fused, out)
            entry["block_rise"] = blockiness_index(out) - blocks
            rec.setdefault("ringing_tried", []).append(entry)
            if entry["ringing_index"] <= limit and entry["block_rise"] <= BLOCK_RISE_MAX:
                self.deblur = candidate
                return entry
        return None

    def _no_deblur(self, rec: dict, note: str) -> None:
        self.note = rec["note"] = note
        self.record = rec

    def _guard_note(self, rec: dict, key: str, full: float) -> None:
        """The note when the guard weakened the deblur (``rec[key]`` below ``full``, a stiffer prior) or stopped it."""
        if self.deblur is None:
            self.note = "no deblurring: every deblur of the estimated blur overshoots the edges or the codec's blocks"
        elif rec[key] < full:
            name = {"sigma_px": "σ", "lambda_over_d_px": "λ/(D·ifov)"}[key]
            self.note = f"deblurring at {name} {rec[key]:.2f} px, weakened from {full:.2f} by the ringing guard"
        if self.deblur is not None and rec.get("prior", self.prior) != self.prior:  # the stiffer prior: why
            own = [t for t in rec["ringing_tried"] if t.get("prior") == self.prior and t[key] == rec[key]]
            grid = bool(own) and own[-1]["block_rise"] > BLOCK_RISE_MAX
            why = "lifts the codec's block grid" if grid else "overshoots the edges"
            said = f"the {rec['prior']} prior: the {self.prior} one {why}"
            self.note = f"{self.note}; {said}" if self.note else said

    def describe(self) -> str:
        if self.record is None:
            return "blind (estimated on the first fused frame)"
        if self.deblur is None:
            return "none (blind estimate: nothing to deblur or not reliable)"
        e = self.record["estimate"]
        if self.record.get("shape") == "learned":
            r = self.record
            return (
                f"blind physics Wiener at D/r0 {r['dr0']:.2f}, λ/(D·ifov) {r['lambda_over_d_px']:.2f} px, depth "
                f"modulation {r['modulation']:.2f} (learned estimate)"
            )
        if self.record.get("shape") == "physics":
            return (
                f"blind physics Wiener at λ/(D·ifov) {self.record['lambda_over_d_px']:.2f} px, D/r0 {PHYSICS_DR0:g} "
                f"(edge estimate {e['sigma_px']:.2f} px)"
            )
        return f"blind Gaussian Wiener at σ {self.deblur.sigma_px:.2f} px (edge estimate {e['sigma_px']:.2f} px)"

    def __call__(self, fused: torch.Tensor) -> torch.Tensor:
        if self.record is None:
            self.decide(fused)
        # the estimates, their strength and the guards were made and tuned on means of bilinearly registered frames:
        # the deblur reads the room's bicubic mean as one (blind set +0.03 / +0.10 / +0.07 dB against the bilinear
        # room; deblurring the bicubic mean itself gained more there but lost 0.4–0.6 dB on two of three 1080p clips);
        # a frame it leaves keeps the bicubic mean's detail (docs/clips.md)
        return fused if self.deblur is None else self.deblur(as_bilinear_mean(fused))


__all__ = ["BlindDeblur", "SHAPES"]
