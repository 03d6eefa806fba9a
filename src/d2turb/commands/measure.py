"""`d2turb measure`: turbulence strength (D/r0, r0, Cn², θ0) from a clip of a static scene (docs/measure.md)."""

from __future__ import annotations

import logging
from pathlib import Path

from d2turb.commands.common import (
    OPTICS_FLAGS,
    add_max_pixels_arg,
    add_optics_args,
    measured_optics,
    optics_given,
    parse_params,
)
from d2turb.defaults import DEFAULT_APERTURE_M, DEFAULT_WAVELENGTH_M
from d2turb.errors import D2TurbError

PARAM_KEYS = (*OPTICS_FLAGS, "fps")  # of the old spelling --param KEY=VALUE
log = logging.getLogger("d2turb.commands")


def register(sub):
    p = sub.add_parser(
        "measure",
        help="measure the turbulence strength (D/r0, r0, Cn², θ0) from a clip of a static scene",
        description="Writes DIR/measure.json (D/r0 with a 90 % interval, the seeing angle λ/(r0·ifov) in px, r0, and "
        "with path_length_m the constant-path Cn² and the isoplanatic angle θ0) and prints one line. CLIP is a video "
        "file or a folder of frames. The optics (--aperture, --wavelength, --ifov, --path-length; --fps) default to "
        f"D = {DEFAULT_APERTURE_M:g} m, λ = {DEFAULT_WAVELENGTH_M * 1e9:g} nm, ifov not known; D/r0 depends on them "
        "only through λ/(D·ifov). Clips that cannot be "
        "measured (too few frames, no texture, failed registration) are refused with the reason.",
    )
    p.add_argument("clip", metavar="CLIP", help="video file or folder of frames")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    add_optics_args(
        p,
        None,
        given_only=True,
        ifov_help="default: not known, λ/(D·ifov) marginalised over 0.7-6 px",
        path_help="default: not known, D/r0 and r0 only (Cn² and θ0 need it)",
        wavelength_note="; the middle one is used",
    )
    p.add_argument(
        "--fps", type=float, default=None, help="frame rate, only to give the fitted wind in m/s (default: not known)"
    )
    p.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help=f"old spelling of the optics, kept for one release: {', '.join(PARAM_KEYS)} (use the flags)",
    )
    p.add_argument("--window", type=int, default=None, metavar="N", help="also estimate per window of N frames")
    p.add_argument("--plot", action="store_true", help="write DIR/measure.png: D/r0 per window with its band")
    p.add_argument("--max-frames", type=int, default=None, metavar="N", help="use only the first N frames")
    p.add_argument(
        "--any-width",
        action="store_true",
        help="report the estimate even when its 90 %% interval spans more than 3x (refused by default, naming the "
        "unknown parameter that widens it)",
    )
    p.add_argument("--bootstrap", type=int, default=200, metavar="N", help="resamples for the interval (default 200)")
    add_max_pixels_arg(p)
    p.set_defaults(func=run)


def optics_of(args) -> dict:
    """The optics given (d2turb.sim.Optics fields, and fps): the flags, or their old spelling ``--param KEY=VALUE``."""
    params = parse_params(args.param, PARAM_KEYS)
    given = measured_optics(optics_given(args, params))
    fps = params.pop("fps", None)
    if fps is not None:
        log.warning("--param fps=… is the old spelling of --fps (kept until the next release)")
        if args.fps is not None and args.fps != fps:
            raise D2TurbError(f"fps given twice: --fps {args.fps} and --param fps={fps}")
    fps = args.fps if args.fps is not None else fps
    return {**given, **({"fps": fps} if fps is not None else {})}


def read_clip(path: Path, max_frames: int | None = None) -> list:
    """Frames of a folder of images or of a video file, as (3,H,W) tensors."""
    # lazy: see d2turb.commands
    from d2turb.io import list_images, read_image
    from d2turb.video import is_video, iter_video

    if path.is_dir():
        files = list_images(path)
        if not files:
            raise D2TurbError(f"{path}: no images in the folder")
        return [read_image(f) for f in files[:max_frames]]
    if is_video(path):
        frames = []
        for _, frame in iter_video(path):
            frames.append(frame)
            if max_frames and len(frames) >= max_frames:
                break
        return frames
    raise D2TurbError(f"{path}: not a folder of frames or a video file")


def plot(result: dict, path: Path) -> None:
    # lazy: matplotlib only for --plot
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    wins = result.get("windows") or [{"start_frame": 0, "frames": result["inputs"]["frames"], **result}]
    mid = [w["start_frame"] + w["frames"] / 2 for w in wins]
    fig, ax = plt.subplots(figsize=(6, 3.2), dpi=120)
    ax.fill_between(mid, [w["dr0_ci"][0] for w in wins], [w["dr0_ci"][1] for w in wins], alpha=0.3, label="90 %")
    ax.plot(mid, [w["dr0"] for w in wins], "o-", label="D/r0 per window")
    ax.axhline(result["dr0"], color="k", lw=0.8, ls="--", label=f"clip: {result['dr0']:.2f}")
    ax.set_xlabel("frame")
    ax.set_ylabel("D/r0")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def run(args):
    # lazy: see d2turb.commands
    from d2turb.clip.strength import Optics, measure_clip
    from d2turb.io import check_output_dir, write_json

    given = optics_of(args)
    optics = Optics(**given)
    src = Path(args.clip)
    if not src.exists():
        raise D2TurbError(f"{src}: no such file or directory")
    if args.bootstrap < 0:
        raise D2TurbError(f"--bootstrap must be 0 or more, got {args.bootstrap}")
    if args.max_frames is not None and args.max_frames < 1:
        raise D2TurbError(f"--max-frames must be 1 or more, got {args.max_frames}")
    out = check_output_dir(args.out)
    frames = read_clip(src, args.max_frames)
    result = measure_clip(
        frames, optics, window=args.window, bootstrap=args.bootstrap, extrapolate=args.any_width, seeing_answers=True
    )
    result["clip"] = str(src)
    result["inputs"]["params_given"] = sorted(given)
    if optics.path_length_m is None:
        result["note"] = "no path_length_m: D/r0 and r0 only (Cn² and θ0 need the path length)"
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "measure.json", result)
    if args.plot:
        plot(result, out / "measure.png")
    lo, hi = result["dr0_ci"]
    s_lo, s_hi = result["seeing_px_ci"]
    seeing = f"seeing λ/(r0·ifov) = {result['seeing_px']:.2f} px [{s_lo:.2f}, {s_hi:.2f}]"
    if not result["dr0_determined"] and not args.any_width:  # without the optics the seeing angle is the answer
        line = (
            f"{src.name}: {seeing} (90 %); D/r0 needs the optics: [{lo:.2f}, {hi:.2f}] without them (give --ifov RAD)"
        )
    else:
        line = f"{src.name}: D/r0 = {result['dr0']:.2f} [{lo:.2f}, {hi:.2f}] (90 %), {seeing}"
        line += f", r0 = {100 * result['r0_m']:.2f} cm"
        if result["cn2"] is not None:
            line += f", Cn² = {result['cn2']:.2e} m^-2/3, θ0 = {result['theta0_urad']:.1f} µrad"
        else:
            line += " (no path_length_m: no Cn², θ0)"
    marg = [k for k in result["parameters"]["marginalised"] if k != "wind_and_boiling"]
    line += f"; given: {', '.join(result['parameters']['given']) or 'none'}"
    line += f", marginalised: {', '.join(marg) or 'none'} (+ wind, boiling fitted)"
    if result.get("windows"):
        line += f", {len(result['windows'])} windows"
    print(line + f" -> {out / 'measure.json'}")
    return 0
