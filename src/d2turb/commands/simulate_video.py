"""`d2turb simulate-video`: physically correlated turbulent frames (frozen-flow layers, wind, boiling)."""

from __future__ import annotations

import sys
from pathlib import Path

from d2turb.commands.common import (
    add_depth_arg,
    add_max_pixels_arg,
    add_motion_args,
    add_seed_arg,
    wait_passively,
)
from d2turb.commands.simulate import add_physics_args, make_params
from d2turb.errors import D2TurbError


def register(sub):
    p = sub.add_parser(
        "simulate-video",
        help="simulate a turbulent clip: frozen-flow layers moved by the wind",
        description="Writes DIR/turb/NNNNNN.png per frame, meta.json, turb.mp4 (with the video extra), "
        "and with --save-tilt / --save-flow tilt/NNNNNN.png / flow/NNNNNN.npy. INPUT is a still image "
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
        "--save-flow", action="store_true", help="also write flow/NNNNNN.npy: float32 (2,H,W) forward displacement px"
    )
    p.add_argument("--no-mp4", action="store_true", help="do not write turb.mp4")
    add_physics_args(p)
    add_max_pixels_arg(p)
    wait_passively(p)
    p.set_defaults(func=run)


def _input_frames(path: Path, frames: int | None):
    """(iterator of (3,H,W) frames or a still tensor, number of frames or None, kind)."""
    # lazy: the pipeline (torch) loads when the command runs; d2turb --help starts without it
    from d2turb.io import list_images, read_image
    from d2turb.video import is_video, iter_video

    if path.is_dir():
        files = list_images(path)
        if not files:
            raise D2TurbError(f"{path}: no images in the folder")
        files = files[:frames] if frames else files
        return (read_image(f) for f in files), len(files), "frames"
    if is_video(path):
        return (frame for _, frame in iter_video(path)), frames, "video"
    return read_image(path), frames or 64, "image"


def _remove_stale_frames(out: Path, frames: int, kept: dict[str, bool]) -> None:
    """Frames an earlier run into ``out`` wrote beyond this run's ``frames`` (and all of those of a kind this run
    did not write), so that turb/, tilt/ and flow/ match meta.json. Only names of this command's pattern
    (six digits) are touched; a folder left empty is removed, and turb.mp4 when the earlier meta.json names it
    and this run wrote none."""
    import json
    import re

    for kind, suffix in (("turb", ".png"), ("tilt", ".png"), ("flow", ".npy")):
        folder = out / kind
        if not folder.is_dir():
            continue
        for p in folder.iterdir():
            m = re.fullmatch(r"(\d{6})" + re.escape(suffix), p.name)
            if m and (not kept[kind] or int(m.group(1)) >= frames) and p.is_file():
                p.unlink()
        if not kept[kind] and not any(folder.iterdir()):
            folder.rmdir()
    if not kept["mp4"] and (out / "turb.mp4").is_file() and (out / "meta.json").is_file():
        try:
            earlier = json.loads((out / "meta.json").read_text())
        except (OSError, ValueError):
            earlier = None
        if isinstance(earlier, dict) and earlier.get("mp4") == "turb.mp4":
            (out / "turb.mp4").unlink()


def run(args):
    # lazy: the pipeline (torch) loads when the command runs; d2turb --help starts without it
    import contextlib

    import numpy as np
    import torch
    from tqdm import tqdm

    from d2turb.depth import depth_for_image
    from d2turb.device import resolve_device
    from d2turb.io import check_output_dir, to_uint8, write_image, write_json, write_npy
    from d2turb.sim import Simulator, dr0_bin
    from d2turb.sim.sequence import check_sequence_args, wind_speeds
    from d2turb.sim.tilt import path_nodes
    from d2turb.video import VIDEO_HINT, Mp4Writer, can_write_mp4

    src = Path(args.input)
    if not src.exists():
        raise D2TurbError(f"{src}: no such file or directory")
    device = resolve_device(args.device)
    # the input's folder (for a folder of frames, that folder itself) may not be the output folder
    out = check_output_dir(args.out, inputs=[src] if src.is_file() else [src / "frame"])
    check_sequence_args(args.frames, args.fps, args.wind_dir, args.boil)
    wind = args.wind[0] if len(args.wind) == 1 else list(args.wind)
    params = make_params(args, args.dr0)
    t, _ = path_nodes(params.tilt_geometry, params.layer_z_frac, 12)
    speeds = wind_speeds(wind, t)
    source, n_frames, kind = _input_frames(src, args.frames)
    sim = Simulator(params, device=device)
    gen = torch.Generator().manual_seed(args.seed)
    mp4 = None
    if not args.no_mp4:
        if can_write_mp4():
            mp4 = out / "turb.mp4"
        else:
            print(f"note: no mp4 written; {VIDEO_HINT}")

    def depth_of(frame):
        d = depth_for_image(args.depth, src if kind == "image" else None, frame, args.disparity, device)
        return None if d is None else d[None]

    h, w = source.shape[-2:] if kind == "image" else (None, None)
    depth_text = "none" if args.depth == "none" else f"{args.depth}, " + ("once" if kind == "image" else "per frame")
    print(
        f"{src.name}: simulating {n_frames} frames"
        + (f" of {w}x{h}" if h else "")
        + f" at D/r0 = {params.dr0:.3g} (depth: {depth_text}); each frame is written to {out / 'turb'} as it is done, "
        "the bar's time estimate follows the first one",
        file=sys.stderr,
        flush=True,
    )
    if kind == "image":
        image, depth = source[None], depth_of(source)
    else:  # a moving input: depth (if any) per frame
        image, depth = (f[None] for f in source), (None if args.depth == "none" else depth_of)
    seq = sim.sequence(
        image,
        frames=n_frames,
        fps=args.fps,
        wind=wind,
        wind_dir=args.wind_dir,
        boil=args.boil,
        depth=depth,
        generator=gen,
    )
    written, size, mean_mod = 0, None, []
    with contextlib.ExitStack() as stack:
        writer = None if mp4 is None else stack.enter_context(Mp4Writer(mp4, args.fps))
        for i, res in enumerate(tqdm(seq, total=n_frames, unit="frame", desc=src.name)):
            write_image(out / "turb" / f"{i:06d}.png", res.turb[0])
            if args.save_tilt:
                write_image(out / "tilt" / f"{i:06d}.png", res.tilt[0])
            if args.save_flow:
                write_npy(out / "flow" / f"{i:06d}.npy", res.flow[0].detach().cpu().numpy().astype(np.float32))
            if writer is not None:
                writer.write(to_uint8(res.turb[0]))
            size = tuple(res.turb.shape[-2:])
            mean_mod.append(float(res.modulation.mean()))
            written += 1
        if written == 0:
            raise D2TurbError(f"{src}: no frames to simulate")
    kept = {"turb": True, "tilt": args.save_tilt, "flow": args.save_flow, "mp4": mp4 is not None}
    try:
        _remove_stale_frames(out, written, kept)
    except OSError as exc:
        raise D2TurbError(f"cannot remove the frames of an earlier run in {out}: {exc.strerror or exc}") from exc
    p = sim.params
    meta = p.to_dict()
    ifov_l = p.ifov_rad * p.path_length_m  # m per px at the object
    meta.update(
        input=str(src),
        input_kind=kind,
        frames=written,
        fps=args.fps,
        wind_m_s=wind,
        wind_dir_deg=args.wind_dir,
        boil=args.boil,
        layers=[
            {
                "z_frac": float(z),
                "wind_m_s": float(v),
                "s_per_frame": float(v / args.fps / (p.aperture_m * (1 - z))),
                "px_per_frame": float(v / args.fps / (ifov_l * z)),
            }
            for z, v in zip(t, speeds)
        ],
        dr0=float(p.dr0),
        bin=dr0_bin(p.dr0),
        seed=args.seed,
        depth=args.depth,
        height=size[0],
        width=size[1],
        mean_modulation=float(np.mean(mean_mod)),
        mp4=mp4.name if mp4 is not None else None,
    )
    write_json(out / "meta.json", meta)
    # the wind's shift per frame of each layer's phase screen over the width of the beam there (meta.json: layers,
    # s_per_frame): consecutive frames decorrelate as it nears 1 (px_per_frame is the same shift at the object's
    # scale, huge for layers near the camera: not an image motion, so not printed)
    near = min(meta["layers"], key=lambda m: m["z_frac"])["s_per_frame"]  # the layers that weigh most in the tilt
    print(
        f"{src.name}: {written} frames of {size[1]}x{size[0]}, D/r0 = {p.dr0:.3g}; the wind moves the turbulence near "
        f"the camera {near:.2g} beam widths per frame (frame-to-frame tilt decorrelates as this nears 1; per layer: "
        f"meta.json) -> {out}" + (f" ({mp4.name})" if mp4 else "")
    )
    return 0
