"""`d2turb restore`: restore images, image folders or a video with a trained model (tiled, any size)."""

from __future__ import annotations

import sys
from pathlib import Path

from d2turb.commands.common import (
    FileErrors,
    add_device_arg,
    add_fail_fast_arg,
    add_max_pixels_arg,
    add_param_arg,
    add_png_level_arg,
    parse_params,
    summary,
)
from d2turb.errors import D2TurbError


def register(sub):
    p = sub.add_parser(
        "restore",
        help="restore turbulence-degraded images (any size, tiled)",
        description="Restore images, folders of frames or a video. Writes NAME_restored.png "
        "(and NAME_flow.npy / NAME_deblurred.png on request) into --out, and NAME.mp4 for a video input (video "
        "extra). With --temporal N, each input is a clip (a video file or a folder of frames) restored across "
        "frames: registration to a sliding window of N frames, fusion, deblurring (docs/clips.md). Unreadable "
        "inputs are reported (one error line each) and skipped; the exit status is then 1.",
    )
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="image files, folders of images, or a video file")
    p.add_argument(
        "--weights",
        default=None,
        help="a .safetensors file from save_pretrained, a weights name looked up in $D2TURB_WEIGHTS_DIR, "
        "~/.cache/d2turb/weights and the package resources, or 'input' (identity baseline); default: the "
        "recommended shipped model (d2turb models lists it)",
    )
    clip = p.add_argument_group("clips (--temporal)")
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
        "clip's first 64 frames) or a weights name/path; default auto: physics, or none when D/r0 can be neither "
        "given nor measured",
    )
    clip.add_argument(
        "--dr0", type=float, default=None, metavar="X", help="D/r0 of the path for --deblur physics (default: measured)"
    )
    add_param_arg(clip, "optics: aperture_m, wavelength_m, ifov_rad (default Nyquist), path_length_m")
    clip.add_argument("--passes", type=int, default=2, metavar="K", help="registration rounds (default 2)")
    clip.add_argument(
        "--preset",
        default="fast",
        choices=["fast", "medium", "fine"],
        help="registration (DIS): fast = flow at half resolution (default), medium/fine = full resolution, slower",
    )
    clip.add_argument("--fusion", default="mean", choices=["mean", "robust"], help="fusion of the registered frames")
    clip.add_argument("--fps", type=float, default=None, help="frame rate of the mp4 of a folder clip (default 30)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--tile", type=int, default=512, help="tile size in pixels (default 512)")
    p.add_argument("--overlap", type=int, default=64, help="pixels shared by neighbouring tiles (default 64)")
    add_device_arg(p)
    p.add_argument(
        "--save-flow",
        action="store_true",
        help="also write NAME_flow.npy, float32 (2, H, W), x then y, px (clips: flow/NNNNNN.npy, forward "
        "displacement of each frame from the restored one, as simulate-video --save-flow)",
    )
    p.add_argument("--save-intermediate", action="store_true", help="also write NAME_deblurred.png (Î_tilt)")
    add_png_level_arg(p)
    add_max_pixels_arg(p)
    add_fail_fast_arg(p)
    p.set_defaults(func=run)


def split_inputs(inputs: list[str]) -> tuple[list[Path], list[Path]]:
    """(image files, video files) named on the command line; output names must be unique."""
    # lazy: the pipeline (torch) loads when the command runs; d2turb --help starts without it
    from d2turb.io import check_unique_stems, expand_inputs
    from d2turb.video import is_video

    images, videos = [], []
    for item in inputs:
        p = Path(item)
        if is_video(p):
            videos.append(p)
        else:
            images.extend(expand_inputs([item]))
    check_unique_stems(images + videos)
    return images, videos


def _save(out_dir: Path, stem: str, details: dict, save_flow: bool, save_intermediate: bool, png_level: int) -> None:
    # lazy: the pipeline (torch) loads when the command runs; d2turb --help starts without it
    import numpy as np

    from d2turb.io import write_image, write_npy

    write_image(out_dir / f"{stem}_restored.png", details["restored"], png_level)
    if save_flow:
        write_npy(out_dir / f"{stem}_flow.npy", details["flow"].numpy().astype(np.float32))
    if save_intermediate:
        write_image(out_dir / f"{stem}_deblurred.png", details["deblurred"], png_level)


def _named(path: Path, exc: D2TurbError) -> D2TurbError:
    return exc if str(exc).startswith(str(path)) else D2TurbError(f"{path}: {exc}")


def run(args) -> int:
    # lazy: the pipeline (torch) loads when the command runs; d2turb --help starts without it
    import contextlib

    from tqdm import tqdm

    from d2turb.device import resolve_device
    from d2turb.io import BackgroundWriter, check_output_dir, read_image
    from d2turb.restore import Restorer
    from d2turb.video import Mp4Writer, can_write_mp4, iter_video, video_fps

    if args.temporal is not None:
        return run_clips(args)
    images, videos = split_inputs(args.inputs)
    out_dir = check_output_dir(args.out, inputs=images + videos)
    restorer = Restorer(
        args.weights, device=resolve_device(args.device), tile=args.tile, overlap=args.overlap, progress=True
    )
    errors = FileErrors(len(images) + len(videos), args.fail_fast)
    options = (args.save_flow, args.save_intermediate, args.png_level)
    count = 0
    with BackgroundWriter(max_pending=4, compute_device=restorer.device) as writer:
        for path in tqdm(images, desc="restore", unit="img", disable=len(images) < 2):
            try:
                image = read_image(path)
                writer.before_compute()
                details = restorer.restore_with_details(image)
            except D2TurbError as exc:
                errors.record(_named(path, exc))
                continue
            writer.submit(_save, out_dir, path.stem, details, *options)
            count += 1
        for video in videos:
            bar = tqdm(iter_video(video), desc=video.name, unit="frame")
            frames = iter(bar)
            with contextlib.ExitStack() as stack:
                mp4 = None
                if can_write_mp4():  # the restored clip as a video too, at the input's frame rate
                    mp4 = stack.enter_context(Mp4Writer(out_dir / f"{video.stem}.mp4", video_fps(video)))
                while True:
                    try:
                        i, frame = next(frames, (None, None))
                        if frame is None:
                            break
                        writer.before_compute()
                        details = restorer.restore_with_details(frame)
                    except D2TurbError as exc:
                        bar.close()
                        errors.record(_named(video, exc))
                        break
                    writer.submit(_save, out_dir, f"{video.stem}_{i:06d}", details, *options)
                    if mp4 is not None:
                        mp4.write(details["restored"])
                    count += 1
                if mp4 is not None and not mp4.frames:
                    stack.pop_all()
                    mp4.abort()
    print(f"restored {count} image(s) with {restorer.name} into {out_dir}")
    return errors.finish("restore")


def _clip_frames(src: Path, errors):
    """(frame names, iterator of (3,H,W) frames) of a clip; an unreadable frame of a folder is reported and
    skipped, a video that stops decoding ends the clip there (reported)."""
    # lazy: the pipeline (torch) loads when the command runs; d2turb --help starts without it
    from d2turb.io import list_images, read_image
    from d2turb.video import is_video, iter_video

    names: list[str] = []
    if is_video(src):

        def decoded():
            try:
                for i, frame in iter_video(src):
                    names.append(f"{src.stem}_{i:06d}")
                    yield frame
            except D2TurbError as exc:
                errors.record(_named(src, exc))

        return names, decoded()
    if not src.is_dir():
        raise D2TurbError(f"{src}: a clip is a video file or a folder of frames")
    files = list_images(src)
    if not files:
        raise D2TurbError(f"{src}: no images in the folder")

    def read():
        for f in files:
            try:
                frame = read_image(f)
            except D2TurbError as exc:
                errors.record(_named(f, exc))
                continue
            names.append(f.stem)
            yield frame

    return names, read()


MEASURE_FRAMES = 64  # frames from the clip's start used to measure D/r0 when --dr0 is not given


def _measured_dr0(src: Path, params: dict) -> float:
    """D/r0 measured on the clip's first MEASURE_FRAMES frames (d2turb.measure); D2TurbError if it cannot be."""
    # lazy: the pipeline (torch) loads when the command runs; d2turb --help starts without it
    import itertools
    from types import SimpleNamespace

    from d2turb.measure import measure_clip

    quiet = SimpleNamespace(record=lambda exc: None)  # bad frames are reported once, by the restoring pass
    _, frames = _clip_frames(src, quiet)
    head = list(itertools.islice(frames, MEASURE_FRAMES))
    optics = {k: params[k] for k in ("aperture_m", "wavelength_m", "ifov_rad", "path_length_m") if k in params}
    return float(measure_clip(head, optics, bootstrap=50)["dr0"])


def _clip_deblur(args, device, src: Path):
    """The deblur step of --temporal: (None, a PhysicsDeblur or a model's restore, its description)."""
    # lazy: the pipeline (torch) loads when the command runs; d2turb --help starts without it
    from d2turb.restore import Restorer
    from d2turb.restore.clip import PhysicsDeblur
    from d2turb.sim import TurbulenceParams

    choice = args.deblur
    if choice == "none":
        return None, "none"
    if choice in ("physics", "auto"):
        params = parse_params(args.param)
        dr0, source = args.dr0, "given"
        if dr0 is None:
            try:
                dr0, source = _measured_dr0(src, params), "measured on the clip"
            except D2TurbError as exc:
                if choice == "physics":
                    raise D2TurbError(f"--deblur physics needs the turbulence strength: give --dr0 X ({exc})") from exc
                print(f"note: no deblurring: {exc}", file=sys.stderr)
                return None, "none (D/r0 could not be measured)"
        try:
            p = TurbulenceParams(**{k: v for k, v in params.items() if k != "path_length_m"}, dr0=min(dr0, 10.0))
        except TypeError as exc:
            raise D2TurbError(f"--param: {exc}") from exc
        lambda_over_d_px = p.reference_wavelength / (p.aperture_m * p.ifov_rad)
        deblur = PhysicsDeblur(p.dr0, lambda_over_d_px)
        return deblur, f"physics (D/r0 {p.dr0:.3g} {source}, λ/D {lambda_over_d_px:.3g} px)"
    restorer = Restorer(choice, device=device, tile=args.tile, overlap=args.overlap)
    return restorer.restore, restorer.name


def run_clips(args) -> int:
    """``restore CLIP --temporal N``: register, fuse and deblur across frames (d2turb.restore.clip)."""
    # lazy: the pipeline (torch) loads when the command runs; d2turb --help starts without it
    import contextlib

    import numpy as np
    from tqdm import tqdm

    from d2turb.device import resolve_device
    from d2turb.io import BackgroundWriter, check_output_dir, list_images, write_image, write_npy
    from d2turb.ops.splat import backward_flow
    from d2turb.restore.clip import ClipRestorer
    from d2turb.video import VIDEO_HINT, Mp4Writer, can_write_mp4, is_video, video_fps

    if len(args.inputs) != 1:
        n = len(args.inputs)
        raise D2TurbError(f"--temporal restores one clip per run (a video or a folder of frames), not {n}")
    src = Path(args.inputs[0])
    if not src.exists():
        raise D2TurbError(f"{src}: no such file or directory")
    if args.fps is not None and not (np.isfinite(args.fps) and args.fps > 0):
        raise D2TurbError(f"--fps must be positive, got {args.fps}")
    restorer = ClipRestorer(temporal=args.temporal, passes=args.passes, fusion=args.fusion, preset=args.preset)
    device = resolve_device(args.device)
    deblur, deblur_name = _clip_deblur(args, device, src)
    restorer.deblur = deblur
    out_dir = check_output_dir(args.out, inputs=list_images(src) if src.is_dir() else [src])
    errors = FileErrors(2, args.fail_fast)  # per frame: a bad one is reported and skipped
    names, frames = _clip_frames(src, errors)
    fps = video_fps(src) if is_video(src) else (args.fps or 30.0)
    # a video keeps its name (its folder cannot be --out); a folder's mp4 is marked, so a user's CLIP.mp4 beside the
    # frames is never replaced
    mp4 = out_dir / (f"{src.stem}.mp4" if is_video(src) else f"{src.resolve().name}_restored.mp4")
    if not can_write_mp4():
        print(f"note: no mp4 written; {VIDEO_HINT}")
        mp4 = None
    print(f"restoring {src} over windows of {args.temporal} frames, deblur: {deblur_name}", file=sys.stderr)
    count = 0
    with contextlib.ExitStack() as stack:
        writer = stack.enter_context(BackgroundWriter(max_pending=4, compute_device=device))
        video = None if mp4 is None else stack.enter_context(Mp4Writer(mp4, fps))
        for out in tqdm(restorer.restore(frames), desc=src.name, unit="frame"):
            stem = names[out.index]
            writer.submit(write_image, out_dir / f"{stem}_restored.png", out.restored, args.png_level)
            if args.save_intermediate:
                writer.submit(write_image, out_dir / f"{stem}_fused.png", out.fused, args.png_level)
            if args.save_flow:  # forward displacement: frame(x) ≈ restored(x + Δ(x)), the inverse of bwd_flow_px
                fwd = backward_flow(out.bwd_flow_px[None])[0].numpy().astype(np.float32)
                writer.submit(write_npy, out_dir / "flow" / f"{out.index:06d}.npy", fwd)
            if video is not None:
                video.write(out.restored)
            count += 1
    print(f"restored {count} frame(s) of {src.name} into {out_dir}" + (f" ({mp4.name})" if mp4 else ""))
    return summary("restore", count + len(errors.failed), len(errors.failed))
