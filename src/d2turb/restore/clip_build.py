"""The one place that builds the :class:`~d2turb.clip.ClipRestorer` of ``d2turb restore CLIP --temporal N`` with
its deblur (``restore --temporal``, ``evaluate --real-clips`` and the page all call :func:`clip_restorer`, so their
defaults agree), and the options it reads (:class:`ClipOptions`)."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

from d2turb.clip import ClipRestorer, PhysicsDeblur
from d2turb.clip.blind import BlindDeblur
from d2turb.clip.live import DEFAULT_PRESET, LIVE_PRESET, PRESETS, LiveRestorer, dis_preset
from d2turb.clip.strength import estimate_words, measure_clip, undetermined_dr0
from d2turb.defaults import DEFAULT_FUSION, DEFAULT_OVERLAP_PX, DEFAULT_TILE_PX, FUSION_WITHOUT_DEBLUR
from d2turb.errors import D2TurbError
from d2turb.io.formats import to_restorer
from d2turb.restore.clip_source import RGB_FLOAT, Clip, open_clip
from d2turb.restore.files import RestoreOptions
from d2turb.restore.single import Restorer
from d2turb.sim import Optics
from d2turb.sim.optics import positive_finite
from d2turb.sim.params import MAX_DR0


@dataclasses.dataclass(frozen=True)
class ClipOptions(RestoreOptions):
    """The options of :func:`restore_clip_files` (``d2turb restore --temporal``) and :func:`clip_restorer`, besides
    :class:`RestoreOptions`'.

    Args:
        deblur, dr0, optics: see :func:`clip_deblur`.
        passes: registration rounds.
        preset: a key of :data:`d2turb.clip.live.PRESETS`: "balanced" (the default: DIS "fast"), "medium", "fine", or
            "fast": the live restorer (:class:`~d2turb.clip.live.LiveRestorer`).
        fusion: fusion of the registered frames; None: the sharpest with ``deblur="none"``, the mean before a deblur
            (:attr:`fusion_used`).
        fps: frame rate of a folder clip's mp4 (None: 30).
        linear_light: deblur in linear light (:class:`~d2turb.clip.ClipRestorer`'s ``linear_light``).
        lookahead: output t waits for input t + lookahead at most (:class:`~d2turb.clip.ClipRestorer`'s); None:
            centred windows for a file, :func:`~d2turb.clip.frames.stream_lookahead` for a stream
            (:func:`~d2turb.restore.clips.restore_clip_files`).
    """

    deblur: str = "auto"
    dr0: float | None = None
    optics: Optics | None = None
    passes: int = 2
    preset: str = DEFAULT_PRESET
    fusion: str | None = None
    fps: float | None = None
    linear_light: bool = False
    lookahead: int | None = None

    @property
    def fusion_used(self) -> str:
        """The fusion the clip gets: ``fusion`` if given, else the sharpest without a deblur (the sharper frame) and the
        mean before one (the Wiener filter models the mean's blur; docs/clips.md)."""
        if self.fusion is not None:
            return self.fusion
        return FUSION_WITHOUT_DEBLUR if self.deblur == "none" else DEFAULT_FUSION


DIS_OF_DEFAULT = PRESETS[DEFAULT_PRESET]


def check_clip_settings(temporal: int, o: ClipOptions) -> str:
    """D2TurbError, in one line, for settings a restorer refuses (an unknown ``preset``, settings the live preset does
    not have, those :meth:`ClipRestorer.check_settings` refuses); else the DIS preset of ``o.preset`` (the live
    one's: the default's, whose checks its own settings pass)."""
    dis = dis_preset(o.preset)
    if dis is None:
        _check_live(o)
    ClipRestorer.check_settings(temporal, o.passes, o.fusion_used, dis or DIS_OF_DEFAULT, o.lookahead)
    return dis or DIS_OF_DEFAULT


def _check_live(o: ClipOptions) -> None:
    if o.passes != 2 or o.fusion not in (None, "mean") or o.linear_light:
        raise D2TurbError(
            f"--preset {LIVE_PRESET} (live) registers each frame in one pass and fuses by the mean, in sRGB values: "
            "--passes, --fusion and --linear-light go with the other presets"
        )


MEASURE_FRAMES = 64  # frames from the clip's start used to measure D/r0 when it is not given


def _clip_head(clip) -> list:
    """The clip's first MEASURE_FRAMES readable frames: an open :class:`Clip`'s, decoded once (it yields them again to
    the restorer, which reports its bad frames), or those of a clip at a path (opened for them alone, its bad frames
    left to the caller's own reading)."""
    if not isinstance(clip, Clip):
        clip = open_clip(clip, SimpleNamespace(record=lambda exc: None))
    return clip.head(MEASURE_FRAMES)


def _measured(clip, optics: Optics) -> dict:
    """``d2turb measure``'s result on the clip's first frames (the same estimates and intervals: what ``restore`` calls
    measured, ``measure`` measures: the frames as float RGB, (H,W,3) here as the restorer holds them, the same grey as
    measure's (3,H,W) tensors); D2TurbError where measure refuses, or where D/r0 is not determined (the physics deblur
    needs it), said in measure's terms: the seeing angle without the camera."""
    head = _clip_head(clip)
    try:
        measured = measure_clip((to_restorer(f, RGB_FLOAT) for f in head), optics, bootstrap=50)
        if not measured["dr0_determined"]:
            raise D2TurbError(undetermined_dr0(measured))
    except D2TurbError as exc:
        raise D2TurbError(f"--deblur physics needs the turbulence strength: give --dr0 X ({exc})") from exc
    return measured


def _physics_deblur(clip, dr0, optics: Optics | None, fusion: str):
    """:func:`clip_deblur`'s physics deblur: at ``dr0``, or at what ``d2turb measure`` finds on the clip's first
    MEASURE_FRAMES frames, at the λ/(D·ifov) of the given ifov, or of the measured estimate, or Nyquist's."""
    optics = Optics() if optics is None else optics
    source, measured = "given (--dr0)", None
    sampling = "given" if optics.ifov_known else "Nyquist (default)"
    if dr0 is None:
        measured = _measured(clip, optics)
        dr0 = measured["dr0"]
        frames = measured["inputs"]["frames"]
        source = f"measured on the clip's first {frames} frames (d2turb measure, 90 %: {estimate_words(measured)})"
        if not optics.ifov_known:  # the λ/(D·ifov) at which measure's estimate holds
            ifov = optics.wavelength_m / (optics.aperture_m * measured["lambda_over_d_px"])
            optics = dataclasses.replace(optics, ifov_rad=ifov)
            sampling = "λ/(D·ifov) of d2turb measure's estimate"
    dr0 = positive_finite("dr0", min(dr0, MAX_DR0))
    optics.check_sampling()
    q = optics.lambda_over_d_px
    deblur = PhysicsDeblur.for_fusion(dr0, q, fusion)
    model = "" if deblur.dr0 == dr0 else f"; OTF at D/r0 {deblur.dr0:.3g} after the sharpest fusion"
    record = {
        "method": "physics",
        "dr0": dr0,
        "dr0_source": source,
        **({k: measured[k] for k in ("dr0_ci", "seeing_px", "seeing_px_ci")} if measured else {}),
        "otf_dr0": deblur.dr0,
        "lambda_over_d_px": q,
        "optics": sampling,
        "balance": deblur.balance,
        "prior": deblur.prior,
    }
    return deblur, f"physics (D/r0 {dr0:.3g} {source}, λ/D {q:.3g} px{model})", record


def clip_deblur(
    choice: str,
    clip,
    *,
    dr0=None,
    optics: Optics | None = None,
    device="cpu",
    tile=DEFAULT_TILE_PX,
    overlap=DEFAULT_OVERLAP_PX,
    fusion=DEFAULT_FUSION,
):
    """The deblur step of a clip: (None, a PhysicsDeblur, a BlindDeblur or a model's restore; its description; a
    record of the value used and where it came from, for the output folder's restore.json).

    Args:
        choice: ``none``; ``physics`` (Wiener with the turbulence OTF at ``dr0``, or at the D/r0 that
            ``d2turb measure`` finds on the first MEASURE_FRAMES frames of ``clip``, an open :class:`Clip` or a path:
            refused where it is not determined);
            ``auto`` (physics at a given ``dr0``; else the blind deblur of :class:`~d2turb.clip.blind.BlindDeblur`,
            estimated on the fused frames of the one restoring pass: no second decode or registration); or a
            weights name/path.
        optics: the optics given (:class:`~d2turb.sim.Optics`; None: the defaults); without its ifov the OTF is at
            the λ/(D·ifov) of the measured estimate, or with ``dr0`` at Nyquist's.
        fusion: the clip's fusion; after ``sharpest`` the physics deblur models a weaker blur
            (:meth:`~d2turb.clip.PhysicsDeblur.for_fusion`) and the blind one keeps the Laplacian prior.
    """
    if choice == "none":
        return None, "none", {"method": "none"}
    if choice == "auto" and dr0 is None:
        blind = BlindDeblur(fusion=fusion)
        return blind, blind.describe(), None  # the record comes from the deblur once it has seen a fused frame
    if choice in ("physics", "auto"):
        return _physics_deblur(clip, dr0, optics, fusion)
    restorer = Restorer(choice, device=device, tile=tile, overlap=overlap)
    return restorer.restore, restorer.name, {"method": "model", "weights": restorer.name}


def clip_restorer(
    clip, temporal: int, options: ClipOptions | None = None, **kwargs
) -> tuple[ClipRestorer, str, dict | None]:
    """The :class:`~d2turb.clip.ClipRestorer` of ``d2turb restore CLIP --temporal N`` with its deblur: the one place
    that builds it (``restore --temporal`` and ``evaluate --real-clips`` both call it, so their defaults agree).

    Args:
        clip: the clip, read here only when the physics deblur measures D/r0 on its first frames: an open
            :class:`~d2turb.restore.clip_source.Clip` (those frames decoded once: the clip yields them again to the
            restorer) or a path (a video file or a folder of frames, opened for them alone).
        temporal: frames per window.
        options: :class:`ClipOptions` (None: restore's defaults; ``kwargs``: its fields by name, in place of those);
            of them this reads deblur, dr0, optics, device, tile, overlap (see :func:`clip_deblur`) and passes,
            preset, fusion (:attr:`ClipOptions.fusion_used`).

    Returns:
        (the restorer with its deblur; the deblur's description; its record for restore.json, None for the
        blind deblur until it has seen a fused frame: then ``restorer.deblur.record``).
    """
    o = ClipOptions.of(options, **kwargs)
    fusion = o.fusion_used
    dis = check_clip_settings(temporal, o)  # before the physics deblur reads the clip
    deblur, name, record = clip_deblur(
        o.deblur, clip, dr0=o.dr0, optics=o.optics, device=o.device, tile=o.tile, overlap=o.overlap, fusion=fusion
    )
    deblur = "none" if deblur is None else deblur
    if dis_preset(o.preset) is None:
        return LiveRestorer(temporal, deblur=deblur), name, record
    settings = {"passes": o.passes, "fusion": fusion, "preset": dis, "linear_light": o.linear_light}
    settings["lookahead"] = o.lookahead
    return ClipRestorer(temporal=temporal, deblur=deblur, **settings), name, record
