"""`d2turb make-dataset`: paired turbulence dataset from folders of clean images (restartable, torchrun-ready)."""

from __future__ import annotations

import json

from d2turb.commands.common import (
    add_depth_arg,
    add_device_arg,
    add_max_pixels_arg,
    add_motion_args,
    add_optics_args,
    add_param_arg,
    add_png_level_arg,
    add_seed_arg,
    optics_given,
    parse_params,
    wait_passively,
)
from d2turb.defaults import DEFAULT_PATH_LENGTH_M
from d2turb.errors import D2TurbError


def register(sub):
    p = sub.add_parser(
        "make-dataset",
        help="generate turb/tilt/gt/flow/depth training or test pairs",
        description="Generate paired samples. Restartable: rerun the same command after an interruption. "
        "Scales out with `torchrun --nproc_per_node N -m d2turb make-dataset ...`.",
    )
    p.add_argument("--clean", nargs="+", required=True, metavar="DIR", help="folders (or files) of clean images")
    p.add_argument("--out", required=True, metavar="DIR", help="output dataset folder")
    p.add_argument("--pairs", type=int, required=True, metavar="N", help="number of samples")
    p.add_argument("--patch", type=int, default=256, help="crop size in px (default 256)")
    p.add_argument(
        "--split",
        choices=["train", "test"],
        default="train",
        help="train: D/r0 uniform over the bins' union; test: balanced, bin = bins[i %% n_bins]",
    )
    p.add_argument("--bins", default="weak,medium,strong", help="comma-separated D/r0 bins (default all three)")
    add_depth_arg(p, "none | prior | DIR | anything:PATH")
    p.add_argument(
        "--depth-is-disparity",
        dest="disparity",
        action="store_true",
        help="maps in a --depth DIR hold disparity (inverse depth, near = large)",
    )
    add_seed_arg(p, "dataset seed (default 0)")
    p.add_argument("--batch", type=int, default=8, help="samples per simulator call (part of the seed; default 8)")
    add_device_arg(p)
    add_optics_args(
        p,
        path_help=f"default {DEFAULT_PATH_LENGTH_M:g}",
        given_only=True,
        ifov_help="default Nyquist λ/(2D); with --geometry fixed",
    )
    add_param_arg(
        p,
        "TurbulenceParams override KEY=VALUE, e.g. n_zernike=21 (repeatable; the optics' keys are the old "
        "spelling of the flags above, kept for one release)",
    )
    p.add_argument(
        "--geometry",
        default="fixed",
        metavar="NAME",
        help="imaging geometry: fixed (TurbulenceParams defaults + the optics flags and --param) or field "
        "(apertures, ranges and depth offsets drawn per chunk of --batch samples), blind (as field, and λ/(D·ifov) "
        "1-4 px; docs/datasets.md)",
    )
    p.add_argument(
        "--frames", type=int, default=1, metavar="N", help="N > 1: turbulent clips of N frames per sample (filmstrips)"
    )
    add_motion_args(p)  # used with --frames N > 1
    p.add_argument(
        "--camera-noise",
        metavar="LO,HI",
        help="Gaussian camera noise on the turbulent frames, σ drawn per sample uniformly in LO..HI grey levels "
        "(0-255 scale), e.g. 0,3",
    )
    p.add_argument(
        "--jpeg",
        metavar="LO,HI",
        help="JPEG-compress each turbulent frame, quality drawn per sample in LO..HI, e.g. 75,95",
    )
    p.add_argument(
        "--profile",
        choices=["standard", "field"],
        default="standard",
        help="field: field-realistic clips with --frames N (camera shake, moving objects, lens blur, sensor noise, "
        "sRGB tone curve, sharpening, resize, JPEG/H.264/H.265; turbulence on linear light; ground truth per frame; "
        "docs/datasets.md)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_png_level_arg(p)
    add_max_pixels_arg(p)
    wait_passively(p)
    p.set_defaults(func=run)


def run(args):
    # lazy: see d2turb.commands
    from d2turb.data.generate import DatasetConfig, generate_dataset

    params = parse_params(args.param)
    params.update(optics_given(args, params))  # the flags; the optics' keys of --param are their old spelling
    camera = {}
    for key, text, cast in (("noise", args.camera_noise, float), ("jpeg", args.jpeg, int)):
        if text:
            try:
                camera[key] = [cast(v) for v in text.split(",")]
            except ValueError:
                flag = "--camera-noise" if key == "noise" else "--jpeg"
                raise D2TurbError(f"{flag} takes LO,HI, got {text!r}") from None
    cfg = DatasetConfig(
        clean=args.clean,
        out=args.out,
        pairs=args.pairs,
        patch=args.patch,
        split=args.split,
        bins=tuple(b.strip() for b in args.bins.split(",") if b.strip()),
        depth=args.depth,
        depth_is_disparity=args.disparity,
        seed=args.seed,
        batch=args.batch,
        device=args.device,
        params=params,
        geometry=args.geometry,
        png_level=args.png_level,
        camera=camera,
        profile=args.profile,
        frames=args.frames,
        sequence=(
            dict(
                fps=args.fps,
                wind=args.wind[0] if len(args.wind) == 1 else args.wind,
                wind_dir=args.wind_dir,
                boil=args.boil,
            )
            if args.frames != 1
            else {}
        ),
    )
    stats = generate_dataset(cfg, progress=not args.no_progress)
    if stats["rank"] == 0:
        print(json.dumps(stats, sort_keys=True))
    return 0
