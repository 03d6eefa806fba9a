"""`d2turb simulate`: depth-aware turbulence on images (turb, tilt, optional flow, meta)."""

from __future__ import annotations

from d2turb.commands.common import (
    add_depth_arg,
    add_device_arg,
    add_fail_fast_arg,
    add_max_pixels_arg,
    add_optics_args,
    add_png_level_arg,
    add_seed_arg,
)
from d2turb.defaults import BATCH_PIXELS, DEFAULT_BATCH, DEFAULT_PATH_LENGTH_M


def add_physics_args(p, path_length_m: float = DEFAULT_PATH_LENGTH_M):
    """Physical parameters shared by simulate and demo."""
    add_optics_args(p, path_length_m)
    p.add_argument(
        "--modulation",
        default="power_offset",
        choices=["uniform", "linear", "linear_offset", "power", "power_offset"],
        help="depth modulation M (default power_offset)",
    )
    p.add_argument("--offset", type=float, default=0.5, metavar="S", help="baseline offset s of Eq. 1 (default 0.5)")
    add_device_arg(p)


def register(sub):
    p = sub.add_parser(
        "simulate",
        help="simulate depth-aware atmospheric turbulence on images",
        description="Writes NAME_turb.png, NAME_tilt.png (unless --no-tilt), NAME_meta.json "
        "(and NAME_fwd_flow_px.npy with --save-flow) per input. Images of the same size are simulated in batches; "
        "outputs are written in the background. Unreadable inputs are reported (one error line each) and "
        "skipped; the exit status is then 1.",
    )
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="image files or folders")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    strength = p.add_mutually_exclusive_group()
    strength.add_argument("--dr0", type=float, default=None, metavar="X", help="turbulence strength D/r0 (default 3)")
    strength.add_argument(
        "--dr0-range", type=float, nargs=2, default=None, metavar=("A", "B"), help="D/r0 drawn uniformly per image"
    )
    strength.add_argument(
        "--cn2",
        type=float,
        default=None,
        metavar="CN2",
        help="refractive-index structure constant (m^-2/3), constant along the path",
    )
    add_depth_arg(
        p,
        "none | prior | FILE | DIR | anything:PATH",
        " (uniform depth, the weight-free prior, a map, a folder of maps by image stem, or Depth Anything V2 from a "
        "local model folder)",
    )
    p.add_argument(
        "--depth-is-disparity",
        "--disparity",
        dest="disparity",
        action="store_true",
        help="depth maps hold disparity (inverse depth, near = large)",
    )
    add_seed_arg(p, "random seed (default 0); results depend on it, on --batch and on the input list")
    p.add_argument(
        "--batch",
        type=int,
        default=DEFAULT_BATCH,
        metavar="N",
        help=f"images of the same size per simulator call, at most {BATCH_PIXELS} pixels in all "
        f"(default {DEFAULT_BATCH})",
    )
    p.add_argument(
        "--save-flow",
        action="store_true",
        help="also write NAME_fwd_flow_px.npy: float32 (2,H,W) forward displacement Δ px, x then y: "
        "turb(x) ≈ clean(x + Δ(x))",
    )
    p.add_argument("--no-tilt", action="store_true", help="do not write NAME_tilt.png")
    add_png_level_arg(p)
    add_max_pixels_arg(p)
    add_fail_fast_arg(p)
    add_physics_args(p)
    p.set_defaults(func=run)


def physics_params(args, dr0=None):
    """The ``TurbulenceParams`` of the options of :func:`add_physics_args` (and ``--cn2`` where the command has it)."""
    # lazy: see d2turb.commands
    from d2turb.sim import make_params

    return make_params(
        args.aperture,
        args.wavelength,
        args.path_length,
        dr0=dr0,
        cn2=getattr(args, "cn2", None),
        ifov_rad=args.ifov,
        offset_s=args.offset,
        modulation=args.modulation,
    )


def run(args):
    # lazy: see d2turb.commands
    from d2turb.data.simulate import SimulateOptions, simulate_files

    options = SimulateOptions.from_args(args, save_tilt=not args.no_tilt)
    return simulate_files(args.inputs, args.out, physics_params(args, args.dr0), options)
