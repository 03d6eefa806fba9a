"""`d2turb simulate`: depth-aware turbulence on images (turb, tilt, optional flow, meta)."""

from __future__ import annotations

from d2turb.commands.common import (
    FileErrors,
    add_depth_arg,
    add_device_arg,
    add_fail_fast_arg,
    add_max_pixels_arg,
    add_png_level_arg,
    add_seed_arg,
)
from d2turb.errors import D2TurbError

BATCH_PIXELS = 1 << 21  # pixels per simulator call (8 images of 512²): bounds the blur's FFT planes


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
    add_device_arg(p)


def register(sub):
    p = sub.add_parser(
        "simulate",
        help="simulate depth-aware atmospheric turbulence on images",
        description="Writes NAME_turb.png, NAME_tilt.png (unless --no-tilt), NAME_meta.json "
        "(and NAME_flow.npy with --save-flow) per input. Images of the same size are simulated in batches; "
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
        default=8,
        metavar="N",
        help=f"images of the same size per simulator call, at most {BATCH_PIXELS} pixels in all (default 8)",
    )
    p.add_argument(
        "--save-flow",
        action="store_true",
        help="also write NAME_flow.npy: float32 (2,H,W) forward displacement px, x then y",
    )
    p.add_argument("--no-tilt", action="store_true", help="do not write NAME_tilt.png")
    add_png_level_arg(p)
    add_max_pixels_arg(p)
    add_fail_fast_arg(p)
    add_physics_args(p)
    p.set_defaults(func=run)


def make_params(args, dr0=None):
    # lazy: the pipeline (torch) loads when the command runs; d2turb --help starts without it
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


def _batches(items, batch: int):
    """Group (path, dr0, image, depth) items of the same image size into lists of at most ``batch`` images
    and BATCH_PIXELS pixels, in input order per size; at most ~2 batches of images wait in memory."""
    pending: dict[tuple[int, int], list] = {}
    for item in items:
        size = tuple(item[2].shape[-2:])
        group = pending.setdefault(size, [])
        group.append(item)
        if len(group) >= max(1, min(batch, BATCH_PIXELS // (size[0] * size[1]))):
            yield pending.pop(size)
        elif sum(len(g) for g in pending.values()) > 2 * batch:
            yield pending.pop(next(iter(pending)))  # the oldest size
    yield from pending.values()


def _check_depth_spec(spec: str) -> None:
    """Refuse a --depth that cannot work for any image once, rather than once per image."""
    from pathlib import Path

    if spec in ("none", "prior"):
        return
    if spec.startswith("anything:"):
        folder = Path(spec[len("anything:") :])
        if not (folder / "config.json").is_file():
            raise D2TurbError(f"--depth {spec}: {folder} is not a Depth Anything model folder (no config.json)")
    elif not Path(spec).exists():
        raise D2TurbError(f"--depth {spec}: no such depth file or folder (or use none, prior, anything:PATH)")


def _write_outputs(out, name: str, turb, tilt, flow, meta: dict, png_level: int) -> None:
    # lazy: the pipeline (torch) loads when the command runs; d2turb --help starts without it
    from d2turb.io import write_image, write_json, write_npy

    write_image(out / f"{name}_turb.png", turb, png_level)
    if tilt is not None:
        write_image(out / f"{name}_tilt.png", tilt, png_level)
    if flow is not None:
        write_npy(out / f"{name}_flow.npy", flow.numpy().astype("float32"))
    write_json(out / f"{name}_meta.json", meta)


def run(args):
    # lazy: the pipeline (torch) loads when the command runs; d2turb --help starts without it
    import torch

    from d2turb.depth import depth_for_image
    from d2turb.device import resolve_device
    from d2turb.io import (
        BackgroundWriter,
        check_output_dir,
        check_unique_stems,
        expand_inputs,
        read_image,
    )
    from d2turb.sim import Simulator, dr0_bin, sample_dr0

    if args.batch < 1:
        raise D2TurbError(f"--batch must be at least 1, got {args.batch}")
    paths = expand_inputs(args.inputs)
    check_unique_stems(paths)
    _check_depth_spec(args.depth)
    params = make_params(args, args.dr0)
    device = resolve_device(args.device)
    out = check_output_dir(args.out, inputs=paths)
    sim = Simulator(params, device=device)
    gen = torch.Generator().manual_seed(args.seed)
    if args.dr0_range is not None:
        strengths = sample_dr0(len(paths), *args.dr0_range, generator=gen).tolist()
    else:
        strengths = [params.dr0] * len(paths)
    errors = FileErrors(len(paths), args.fail_fast)

    def readable():
        for path, dr0 in zip(paths, strengths):
            try:
                image = read_image(path)
                depth = depth_for_image(args.depth, path, image, is_disparity=args.disparity, device=device)
            except D2TurbError as exc:
                errors.record(exc)
                continue
            yield path, dr0, image, depth

    base_meta = params.to_dict()
    with BackgroundWriter(max_pending=2 * args.batch, compute_device=device) as writer:
        for group in _batches(readable(), args.batch):
            writer.before_compute()
            images = torch.stack([item[2] for item in group])
            depths = (
                None if group[0][3] is None else torch.stack([item[3].reshape(1, *images.shape[-2:]) for item in group])
            )
            dr0 = torch.tensor([item[1] for item in group], dtype=torch.float64)
            res = sim(images, depth=depths, dr0=dr0, generator=gen)
            turb = res.turb.float().cpu()
            tilt = None if args.no_tilt else res.tilt.float().cpu()
            flow = res.flow.float().cpu() if args.save_flow else None
            modulation = res.modulation.flatten(1).mean(1).tolist()
            for b, (path, value, image, _) in enumerate(group):
                meta = dict(
                    base_meta,
                    dr0=float(value),
                    r0_m=params.aperture_m / float(value),
                    bin=dr0_bin(value),
                    seed=args.seed,
                    batch=args.batch,
                    input=str(path),
                    depth=args.depth,
                    height=image.shape[1],
                    width=image.shape[2],
                    mean_modulation=float(modulation[b]),
                )
                writer.submit(
                    _write_outputs,
                    out,
                    path.stem,
                    turb[b],
                    None if tilt is None else tilt[b],
                    None if flow is None else flow[b],
                    meta,
                    args.png_level,
                )
                print(f"{path.name}: D/r0 = {value:.3g} ({dr0_bin(value)}) -> {out / (path.stem + '_turb.png')}")
    return errors.finish("simulate")
