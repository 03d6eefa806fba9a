"""`d2turb restore`: restore images, image folders or a video with a trained model (tiled, any size)."""

from __future__ import annotations

from pathlib import Path

from d2turb.commands.common import FileErrors, add_device_arg, add_fail_fast_arg, add_max_pixels_arg, add_png_level_arg
from d2turb.errors import D2TurbError


def register(sub):
    p = sub.add_parser(
        "restore",
        help="restore turbulence-degraded images (any size, tiled)",
        description="Restore images, folders of frames or a video. Writes NAME_restored.png "
        "(and NAME_flow.npy / NAME_deblurred.png on request) into --out. Unreadable inputs are reported "
        "(one error line each) and skipped; the exit status is then 1.",
    )
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="image files, folders of images, or a video file")
    p.add_argument(
        "--weights",
        help="a .safetensors file from save_pretrained, a weights name looked up in $D2TURB_WEIGHTS_DIR, "
        "~/.cache/d2turb/weights and the package resources, or 'input' (identity baseline); default: the "
        "recommended shipped model (d2turb models lists it)",
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--tile", type=int, default=512, help="tile size in pixels (default 512)")
    p.add_argument("--overlap", type=int, default=64, help="pixels shared by neighbouring tiles (default 64)")
    add_device_arg(p, "cpu")
    p.add_argument("--save-flow", action="store_true", help="also write NAME_flow.npy, float32 (2, H, W), x then y, px")
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
    from tqdm import tqdm

    from d2turb.device import resolve_device
    from d2turb.io import BackgroundWriter, check_output_dir, read_image
    from d2turb.restore import Restorer
    from d2turb.video import iter_video

    images, videos = split_inputs(args.inputs)
    out_dir = check_output_dir(args.out)
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
                count += 1
    print(f"restored {count} image(s) with {restorer.name} into {out_dir}")
    return errors.finish("restore")
