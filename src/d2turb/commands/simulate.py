"""`d2turb simulate`: depth-aware turbulence on images (turb, tilt, optional flow, meta)."""

from __future__ import annotations

from d2turb.errors import D2TurbError


def add_physics_args(p, path_length_m: float = 1000.0):
    """Physical parameters shared by simulate and demo."""
    p.add_argument(
        "--aperture", type=float, default=0.1, metavar="M", help="aperture diameter D in metres (default 0.1)"
    )
    p.add_argument(
        "--wavelength",
        type=float,
        nargs="+",
        default=[525e-9],
        metavar="M",
        help="wavelength in metres, one value or three (R G B) (default 525e-9)",
    )
    p.add_argument(
        "--path-length",
        type=float,
        default=path_length_m,
        metavar="M",
        help=f"path length L in metres (default {path_length_m:g})",
    )
    p.add_argument(
        "--ifov", type=float, default=None, metavar="RAD", help="pixel angular size (default Nyquist λ/(2D))"
    )
    p.add_argument(
        "--modulation",
        default="power_offset",
        choices=["uniform", "linear", "linear_offset", "power", "power_offset"],
        help="depth modulation M (default power_offset)",
    )
    p.add_argument("--offset", type=float, default=0.5, metavar="S", help="baseline offset s of Eq. 1 (default 0.5)")
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")


def register(sub):
    p = sub.add_parser(
        "simulate",
        help="simulate depth-aware atmospheric turbulence on images",
        description="Writes NAME_turb.png, NAME_tilt.png, NAME_meta.json "
        "(and NAME_flow.npy with --save-flow) per input.",
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
    p.add_argument(
        "--depth",
        default="none",
        metavar="none|prior|FILE|DIR|anything:PATH",
        help="relative depth (far = 1): none, the weight-free prior, a map, a folder of maps by image stem, "
        "or Depth Anything V2 from a local model folder",
    )
    p.add_argument(
        "--depth-is-disparity",
        "--disparity",
        dest="disparity",
        action="store_true",
        help="depth maps hold disparity (inverse depth, near = large)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--save-flow",
        action="store_true",
        help="also write NAME_flow.npy: float32 (2,H,W) forward displacement px, x then y",
    )
    add_physics_args(p)
    p.set_defaults(func=run)


def make_params(args, dr0=None):
    from d2turb.sim import TurbulenceParams

    wl = args.wavelength
    if len(wl) not in (1, 3):
        raise D2TurbError(f"--wavelength takes one or three values, got {len(wl)}")
    return TurbulenceParams(
        aperture_m=args.aperture,
        wavelength_m=tuple(wl) if len(wl) == 3 else wl[0],
        path_length_m=args.path_length,
        dr0=dr0,
        cn2=getattr(args, "cn2", None),
        ifov_rad=args.ifov,
        offset_s=args.offset,
        modulation=args.modulation,
    )


def run(args):
    from pathlib import Path

    import torch

    from d2turb.depth import depth_for_image
    from d2turb.io import expand_inputs, read_image, write_image, write_json, write_npy
    from d2turb.sim import Simulator, dr0_bin, sample_dr0

    paths = expand_inputs(args.inputs)
    params = make_params(args, args.dr0)
    out = Path(args.out)
    sim = Simulator(params, device=args.device)
    gen = torch.Generator().manual_seed(args.seed)
    if args.dr0_range is not None:
        strengths = sample_dr0(len(paths), *args.dr0_range, generator=gen).tolist()
    else:
        strengths = [params.dr0] * len(paths)
    for path, dr0 in zip(paths, strengths):
        image = read_image(path)
        depth = depth_for_image(args.depth, path, image, is_disparity=args.disparity, device=args.device)
        res = sim(image[None], depth=None if depth is None else depth[None], dr0=dr0, generator=gen)
        name = path.stem
        write_image(out / f"{name}_turb.png", res.turb[0])
        write_image(out / f"{name}_tilt.png", res.tilt[0])
        if args.save_flow:
            write_npy(out / f"{name}_flow.npy", res.flow[0].detach().cpu().numpy().astype("float32"))
        meta = params.to_dict()
        meta.update(
            dr0=float(dr0),
            r0_m=params.aperture_m / float(dr0),
            bin=dr0_bin(dr0),
            seed=args.seed,
            input=str(path),
            depth=args.depth,
            height=image.shape[1],
            width=image.shape[2],
            mean_modulation=float(res.modulation.mean()),
        )
        write_json(out / f"{name}_meta.json", meta)
        print(f"{path.name}: D/r0 = {dr0:.3g} ({dr0_bin(dr0)}) -> {out / (name + '_turb.png')}")
    return 0
