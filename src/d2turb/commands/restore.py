"""`d2turb restore`: restore images, image folders or a video with a trained model (tiled, any size)."""

from __future__ import annotations

from d2turb.commands.common import (
    OPTICS_FLAGS,
    add_device_arg,
    add_fail_fast_arg,
    add_max_pixels_arg,
    add_optics_args,
    add_param_arg,
    add_png_level_arg,
    optics_given,
    parse_params,
    wait_passively,
)
from d2turb.defaults import CLIP_FUSIONS, DEFAULT_FUSION, DEFAULT_OVERLAP_PX, DEFAULT_TILE_PX, FUSION_WITHOUT_DEBLUR
from d2turb.errors import D2TurbError

# what the live preset gives up (clip.live.LIVE_LOSS_DB and LIVE_LOSS_PLAIN_DB, measured on the blind test set;
# docs/clips.md "The live preset"): literal here, the command line imports no clip code to show its help
LIVE_HELP = (
    "each frame registered once, at half size, no camera following, no moving-object fallback (moving objects "
    "ghost), the blind deblur on the luma, outputs a window behind the input; on the blind test set at most 0.21 dB "
    "below the default per bin (offset removed; 0.03 dB in plain PSNR)"
)


def register(sub):
    p = sub.add_parser(
        "restore",
        help="restore turbulence-degraded images (any size, tiled)",
        description="Restore images, folders of frames or a video. Every output is named after its input "
        "(docs/cli.md): NAME_restored.png (and NAME_bwd_flow_px.npy / NAME_deblurred.png / NAME_compare.png on "
        "request) "
        "into --out, and NAME_restored.mp4 for a video or a clip (video extra). With --temporal N, each input is "
        "a clip (a video file or a folder of frames) restored across frames: registration to a sliding window of "
        "N frames, fusion, deblurring (docs/clips.md). Unreadable inputs are reported (one error line each) and "
        "skipped; the exit status is then 1.",
    )
    p.add_argument(
        "inputs",
        nargs="+",
        metavar="INPUT",
        help="image files (16-bit and grey kept: docs/cli.md), folders of images, a video file; with --temporal also "
        "a SER video, a FITS cube, or a stream read as it comes: - (standard input, e.g. y4m), a URL "
        "(rtsp://, http://, ...) or a capture device (/dev/video0)",
    )
    p.add_argument(
        "--weights",
        default=None,
        help="a .safetensors file from save_pretrained, a weights name looked up in $D2TURB_WEIGHTS_DIR, "
        "~/.cache/d2turb/weights and the package resources, or 'input' (identity baseline); default: the "
        "recommended shipped model (d2turb models lists it)",
    )
    _add_clip_args(p.add_argument_group("clips (--temporal)"))
    p.add_argument(
        "--out",
        required=True,
        help="output folder; with --temporal also - : the restored frames as a y4m stream on standard output",
    )
    p.add_argument("--tile", type=int, default=DEFAULT_TILE_PX, help=f"tile size in pixels (default {DEFAULT_TILE_PX})")
    p.add_argument(
        "--overlap",
        type=int,
        default=DEFAULT_OVERLAP_PX,
        help=f"pixels shared by neighbouring tiles (default {DEFAULT_OVERLAP_PX})",
    )
    add_device_arg(p)
    p.add_argument(
        "--save-flow",
        action="store_true",
        help="also write NAME_bwd_flow_px.npy, float32 (2, H, W), x then y, px: the backward flow V̂, "
        "warp(deblurred, V̂) ≈ restored (clips: fwd_flow_px/NNNNNN.npy, the forward displacement Δ of each frame "
        "from the restored one, frame(x) ≈ restored(x + Δ(x)), as simulate-video --save-flow)",
    )
    p.add_argument("--save-intermediate", action="store_true", help="also write NAME_deblurred.png (Î_tilt)")
    p.add_argument(
        "--compare",
        action="store_true",
        help="also write NAME_compare.png (input | restored, labelled; a clip's or video's middle frame) and for a "
        "clip or video NAME_compare.mp4 (side by side, video extra)",
    )
    add_png_level_arg(p)
    add_max_pixels_arg(p)
    add_fail_fast_arg(p)
    # clips: torch runs only the deblur's FFTs, beside OpenCV's and the writers' threads (a spinning team slows them)
    wait_passively(p, when=lambda args: args.temporal is not None)
    p.set_defaults(func=run)


def _add_clip_args(clip) -> None:
    """The options of ``restore --temporal N`` (a clip restored across frames)."""
    clip.add_argument(
        "--temporal",
        type=int,
        default=None,
        metavar="N",
        help="restore each input as a clip over a sliding window of N frames (N >= 2; e.g. 32)",
    )
    clip.add_argument(
        "--deblur",
        default="auto",
        metavar="none|physics|MODEL",
        help="after fusion: none, physics (Wiener with the turbulence OTF at --dr0, or at the D/r0 measured on the "
        "clip's first 64 frames by d2turb measure, refused when it refuses) or a weights name/path; default auto: "
        "physics at a given --dr0, else a blind deblur: the fused frame's D/r0, λ/(D·ifov) and depth modulation "
        "estimated by a small network from the frame and the registered motion, the physics Wiener filter at them "
        "with a ringing guard (none, with a note, when the frame has too few edges)",
    )
    clip.add_argument(
        "--dr0", type=float, default=None, metavar="X", help="D/r0 of the path for --deblur physics (default: measured)"
    )
    add_optics_args(
        clip,
        None,
        given_only=True,
        ifov_help="default: the λ/(D·ifov) of the measured D/r0; Nyquist λ/(2D) with --dr0",
        path_help="default: not known; used by the measurement only",
        wavelength_note="; the middle one is used",
    )
    add_param_arg(
        clip, "old spelling of the optics, kept for one release: aperture_m, wavelength_m, ifov_rad, path_length_m"
    )
    clip.add_argument(
        "--passes",
        type=int,
        default=2,
        metavar="K",
        help="registration rounds (default 2; 1 is about twice as fast at 1080p but ghosts moving objects more)",
    )
    clip.add_argument(
        "--preset",
        default="balanced",
        choices=["fast", "balanced", "medium", "fine"],
        help="balanced (default): two registration rounds (DIS, the flow at half resolution), the moving-object "
        "fallback, the camera followed; medium/fine: the flow at full resolution, slower; fast: the live preset "
        f"for live cameras (1280x720 at ~5x the default's speed, the mp4 alone written: {LIVE_HELP}; "
        "docs/clips.md). Until 2026-12-08 'fast' named what is now 'balanced'",
    )
    clip.add_argument(
        "--linear-light",
        action="store_true",
        help="deblur in linear light (frames decoded from sRGB, deblurred, encoded): for a camera's 8-bit footage, "
        "where air and optics blurred the light before the tone curve (+0.45 dB on field-realistic clips; on clips "
        "blurred after encoding, as our simulator's, it loses: docs/clips_linear_light.md); the physical deblurs only",
    )
    clip.add_argument(
        "--fusion",
        default=None,
        choices=CLIP_FUSIONS,
        help="fusion of the registered frames: mean, robust, fba (Fourier burst accumulation), sharpest (each pyramid "
        f"coefficient from the frame that kept it best: sharper; docs/clips.md); default {FUSION_WITHOUT_DEBLUR} with "
        f"--deblur none, else {DEFAULT_FUSION} (its blur is the one the deblur models)",
    )
    clip.add_argument(
        "--lookahead",
        type=int,
        default=None,
        metavar="L",
        help="an output waits for the input L frames later at most (the windows of the registration rounds and of "
        "the output reach L frames ahead together, the rest behind); default: centred windows for a file "
        "(3*(N/2 - 1) frames ahead with 2 rounds), N/2 - 1 for a stream (latency: half a window plus the "
        "processing). Its cost on the blind test set (--temporal 32, L 15): +0.03/-0.08/-0.07 dB per bin "
        "(weak/medium/strong) against centred windows (docs/clips.md, streams)",
    )
    clip.add_argument("--fps", type=float, default=None, help="frame rate of the mp4 of a folder clip (default 30)")
    clip.add_argument(
        "--max-frames",
        type=int,
        default=None,
        metavar="N",
        help="restore at most the clip's first N frames (a stream: stop after N); Ctrl-C stops a clip with the "
        "frames so far written and the mp4 finalised",
    )


def run(args) -> int:
    if args.temporal is not None:
        return run_clips(args)
    from d2turb.video import is_stream  # lazy: see d2turb.commands

    if args.max_frames is not None or args.out == "-" or any(is_stream(i) for i in args.inputs):
        raise D2TurbError("a stream (-, a URL, a device), --max-frames and --out - are for clips: give --temporal N")
    # lazy: see d2turb.commands
    from d2turb.restore.files import RestoreOptions, restore_files

    return restore_files(args.inputs, args.out, args.weights, RestoreOptions.from_args(args))


def _optics(args):
    """The optics given for the physics deblur (:class:`~d2turb.sim.Optics`; None: none given): the flags, or their
    old spelling ``--param KEY=VALUE``."""
    from d2turb.sim.optics import Optics  # lazy: see d2turb.commands

    given = optics_given(args, parse_params(args.param, tuple(OPTICS_FLAGS)))
    return Optics(**given) if given else None


def run_clips(args) -> int:
    """``restore CLIP --temporal N``: register, fuse and deblur across frames (d2turb.restore.clips)."""
    # lazy: see d2turb.commands
    from d2turb.restore.clip_build import ClipOptions
    from d2turb.restore.clips import restore_clip_files

    if len(args.inputs) != 1:
        n = len(args.inputs)
        raise D2TurbError(f"--temporal restores one clip per run (a video or a folder of frames), not {n}")
    optics = _optics(args) if args.deblur in ("physics", "auto") else None
    options = ClipOptions.from_args(args, optics=optics)
    return restore_clip_files(args.inputs[0], args.out, args.temporal, options, max_frames=args.max_frames)
