"""`d2turb simulate-video`: physically correlated turbulent frames (frozen-flow layers, wind, boiling)."""

from __future__ import annotations

from d2turb.commands.common import add_depth_arg, add_max_pixels_arg, add_motion_args, add_seed_arg, wait_passively
from d2turb.commands.simulate import add_physics_args, physics_params


def register(sub):
    p = sub.add_parser(
        "simulate-video",
        help="simulate a turbulent clip: frozen-flow layers moved by the wind",
        description="Writes DIR/turb/NNNNNN.png per frame, meta.json, turb.mp4 (with the video extra), "
        "and with --save-tilt / --save-flow tilt/NNNNNN.png / fwd_flow_px/NNNNNN.npy. INPUT is a still image "
        "(the scene stays, the air moves) or a video file / folder of frames (used frame by frame).",
    )
    p.add_argument("input", metavar="INPUT", help="image file, video file, or folder of frames")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--frames", type=int, default=None, metavar="N", help="frames (default: 64, or all input frames)")
    add_motion_args(p)
    strength = p.add_mutually_exclusive_group()
    strength.add_argument("--dr0", type=float, default=None, metavar="X", help="turbulence strength D/r0 (default 3)")
    strength.add_argument("--cn2", type=float, default=None, metavar="CN2", help="Cn² (m^-2/3), constant on the path")
    add_depth_arg(p, "none | prior | FILE | anything:PATH", " (of a video input: per frame)")
    p.add_argument("--depth-is-disparity", "--disparity", dest="disparity", action="store_true")
    add_seed_arg(p)
    p.add_argument("--save-tilt", action="store_true", help="also write tilt-only frames tilt/NNNNNN.png")
    p.add_argument(
        "--save-flow",
        action="store_true",
        help="also write fwd_flow_px/NNNNNN.npy: float32 (2,H,W) forward displacement Δ px: turb(x) ≈ clean(x + Δ(x))",
    )
    p.add_argument("--no-mp4", action="store_true", help="do not write turb.mp4")
    add_physics_args(p)
    add_max_pixels_arg(p)
    wait_passively(p)
    p.set_defaults(func=run)


def run(args):
    # lazy: see d2turb.commands
    from d2turb.data.simulate import simulate_video

    return simulate_video(
        args.input,
        args.out,
        physics_params(args, args.dr0),
        frames=args.frames,
        fps=args.fps,
        wind=args.wind[0] if len(args.wind) == 1 else list(args.wind),
        wind_dir=args.wind_dir,
        boil=args.boil,
        depth=args.depth,
        disparity=args.disparity,
        seed=args.seed,
        save_tilt=args.save_tilt,
        save_flow=args.save_flow,
        mp4=not args.no_mp4,
        device=args.device,
    )
