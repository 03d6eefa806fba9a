"""`d2turb measure`: the seeing angle λ/(r0·ifov) in pixels from a clip of a static scene, and as the optics allow
D/r0, r0, Cn² and θ0 (docs/measure.md)."""

from __future__ import annotations

import logging
import math
import sys
from pathlib import Path

from d2turb.commands.common import (
    OPTICS_FLAGS,
    add_max_pixels_arg,
    add_optics_args,
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
        help="measure the turbulence from a clip of a static scene: the seeing angle in px, D/r0, r0, Cn², θ0",
        description="Writes DIR/measure.json and prints one line: the seeing angle ρ = λ/(r0·ifov) in pixels with its "
        "90 % interval (what a clip measures without the camera's optics) and, as the optics allow, D/r0 (needs "
        "the ifov: --ifov, or --pixel-pitch with --focal-length), r0, and with the distance (--path-length) the "
        "constant-path Cn² and the isoplanatic angle θ0. What is not given is marginalised over a documented range; "
        "when an interval spans more than 3x a note line names what narrows it most. CLIP is a video file or a folder "
        f"of frames. Defaults: D = {DEFAULT_APERTURE_M:g} m, λ = {DEFAULT_WAVELENGTH_M * 1e9:g} nm, ifov and path "
        "not known (docs/measure.md says how to read each from a camera's data sheet). Clips with nothing to "
        "estimate (too few frames, no texture, frames that are not one static scene) are refused with the cause.",
    )
    p.add_argument("clip", metavar="CLIP", help="video file or folder of frames")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    add_optics_args(
        p,
        None,
        given_only=True,
        ifov_help="default: not known, λ/(D·ifov) marginalised over 0.7-6 px",
        path_help="the distance to the scene; default: not known (Cn² and θ0 need it)",
        wavelength_note="; the middle one is used",
    )
    p.add_argument(
        "--pixel-pitch",
        type=float,
        default=None,
        metavar="M",
        help="the sensor's pixel pitch in metres (times its width in px over the frame's, for a resized video); with "
        "--focal-length it gives --ifov = pitch / focal length",
    )
    p.add_argument("--focal-length", type=float, default=None, metavar="M", help="the lens's focal length in metres")
    p.add_argument(
        "--f-number",
        type=float,
        default=None,
        metavar="N",
        help="the lens's f-number as set; with --focal-length it gives --aperture = focal length / N",
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
    p.add_argument("--plot", action="store_true", help="write DIR/measure.png: the estimate per window with its band")
    p.add_argument("--max-frames", type=int, default=None, metavar="N", help="use only the first N frames")
    p.add_argument(
        "--any-width",
        action="store_true",
        help="no effect: the estimate is always reported with its interval (kept for one release)",
    )
    p.add_argument("--bootstrap", type=int, default=200, metavar="N", help="resamples for the interval (default 200)")
    add_max_pixels_arg(p)
    p.set_defaults(func=run)


def _positive(value, flag: str) -> float | None:
    if value is not None and not (math.isfinite(value) and value > 0):
        raise D2TurbError(f"{flag} must be positive, got {value}")
    return value


def _from_camera(given: dict, args) -> dict:
    """``given`` with ifov_rad = pixel pitch / focal length and aperture_m = focal length / f-number where those
    are given; one-line error for a flag without its partner or a value given twice that disagrees."""
    pitch = _positive(getattr(args, "pixel_pitch", None), "--pixel-pitch")
    focal = _positive(getattr(args, "focal_length", None), "--focal-length")
    f_number = _positive(getattr(args, "f_number", None), "--f-number")
    if focal is None and (pitch is not None or f_number is not None):
        raise D2TurbError(f"{'--pixel-pitch' if pitch is not None else '--f-number'} needs --focal-length")
    if focal is not None and pitch is None and f_number is None:
        raise D2TurbError("--focal-length needs --pixel-pitch (for the ifov) or --f-number (for the aperture)")
    derived = {}
    if pitch is not None:
        derived["ifov_rad"] = (pitch / focal, "--pixel-pitch / --focal-length")
    if f_number is not None:
        derived["aperture_m"] = (focal / f_number, "--focal-length / --f-number")
    out = dict(given)
    for key, (value, how) in derived.items():
        if key in out and not math.isclose(out[key], value, rel_tol=1e-3):
            raise D2TurbError(f"{key} given twice: {OPTICS_FLAGS[key]} {out[key]:g} and {how} = {value:g}")
        out[key] = value
    return out


def optics_of(args) -> dict:
    """The optics given (d2turb.sim.Optics fields, and fps): the flags, the camera's (--pixel-pitch, --focal-length,
    --f-number), or their old spelling ``--param KEY=VALUE``."""
    params = parse_params(args.param, PARAM_KEYS)
    given = _from_camera(optics_given(args, params), args)
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
    """DIR/measure.png: the seeing angle ρ per window with its 90 % band and, with ifov given, D/r0 beside it."""
    # lazy: matplotlib only for --plot
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from d2turb.clip.strength import answer_quantity  # with the plot only: the command module stays light for --help

    wins = result.get("windows") or [{"start_frame": 0, "frames": result["inputs"]["frames"], **result}]
    mid = [w["start_frame"] + w["frames"] / 2 for w in wins]
    keys = ["seeing_px"] + (["dr0"] if answer_quantity(result) == "dr0" else [])
    labels = {"seeing_px": "seeing angle ρ = λ/(r0·ifov) (px)", "dr0": "D/r0"}
    fig, axes = plt.subplots(len(keys), 1, figsize=(6, 2.6 * len(keys)), dpi=120, sharex=True, squeeze=False)
    for ax, key in zip(axes[:, 0], keys):
        lo, hi = [w[f"{key}_ci"][0] for w in wins], [w[f"{key}_ci"][1] for w in wins]
        ax.fill_between(mid, lo, hi, alpha=0.3, label="90 %")
        ax.plot(mid, [w[key] for w in wins], "o-", label="per window" if result.get("windows") else "clip")
        ax.axhline(result[key], color="k", lw=0.8, ls="--", label=f"clip: {result[key]:.2f}")
        ax.set_ylabel(labels[key])
        ax.legend(fontsize=8)
    axes[-1, 0].set_xlabel("frame")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def summary_line(name: str, result: dict) -> str:
    """The printed line: ρ first without the camera's ifov (D/r0 only as the interval the clip allows), D/r0 first
    with it; r0, Cn², θ0 as the optics allow; what was given and marginalised."""
    s_lo, s_hi = result["seeing_px_ci"]
    lo, hi = result["dr0_ci"]
    seeing = f"seeing angle ρ = λ/(r0·ifov) = {result['seeing_px']:.2f} px [{s_lo:.2f}, {s_hi:.2f}]"
    if "ifov_rad" not in result["parameters"]["given"]:
        line = (
            f"{name}: {seeing} (90 %); D/r0 and r0 need the camera's ifov: D/r0 within [{lo:.2f}, {hi:.2f}] without it"
        )
    else:
        line = f"{name}: D/r0 = {result['dr0']:.2f} [{lo:.2f}, {hi:.2f}] (90 %), {seeing}"
        line += f", r0 = {100 * result['r0_m']:.2f} cm"
        if result["cn2"] is not None:
            line += f", Cn² = {result['cn2']:.2e} m^-2/3, θ0 = {result['theta0_urad']:.1f} µrad"
        else:
            line += " (no --path-length: no Cn², θ0)"
    marg = [k for k in result["parameters"]["marginalised"] if k != "wind_and_boiling"]
    line += f"; given: {', '.join(result['parameters']['given']) or 'none'}"
    line += f", marginalised: {', '.join(marg) or 'none'} (+ wind, boiling fitted)"
    if result.get("windows"):
        line += f", {len(result['windows'])} windows"
    return line


def run(args):
    # lazy: see d2turb.commands
    from d2turb.clip.strength import Optics, interval_note, measure_clip
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
    if args.any_width:
        log.warning("--any-width has no effect: the estimate is always reported (kept until the next release)")
    out = check_output_dir(args.out)
    frames = read_clip(src, args.max_frames)
    result = measure_clip(frames, optics, window=args.window, bootstrap=args.bootstrap)
    result["clip"] = str(src)
    result["inputs"]["params_given"] = sorted(given)
    note = interval_note(result)
    result["note"] = "; ".join(
        [t for t in (note, "" if optics.path_length_m else "no path_length_m: Cn² and θ0 need the path length") if t]
    )
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "measure.json", result)
    if args.plot:
        plot(result, out / "measure.png")
    print(summary_line(src.name, result) + f" -> {out / 'measure.json'}")
    if note:
        print(f"note: {note}", file=sys.stderr)
    return 0
