"""`d2turb restore`: restore images, image folders or a video with a trained model (tiled, any size)."""

from __future__ import annotations

from pathlib import Path

from d2turb.errors import D2TurbError

VIDEO_SUFFIXES = {".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".gif"}
VIDEO_HINT = "install the video extra: pip install 'd2turb[video]'"


def register(sub):
    p = sub.add_parser(
        "restore",
        help="restore turbulence-degraded images (any size, tiled)",
        description="Restore images, folders of frames or a video. Writes NAME_restored.png "
        "(and NAME_flow.npy / NAME_deblurred.png on request) into --out.",
    )
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="image files, folders of images, or a video file")
    p.add_argument(
        "--weights",
        required=True,
        help="a .safetensors file from save_pretrained, a weights name looked up in $D2TURB_WEIGHTS_DIR, "
        "~/.cache/d2turb/weights and the package resources, or 'input' (identity baseline)",
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--tile", type=int, default=512, help="tile size in pixels (default 512)")
    p.add_argument("--overlap", type=int, default=64, help="pixels shared by neighbouring tiles (default 64)")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="cpu (default) or cuda (bf16 autocast)")
    p.add_argument("--save-flow", action="store_true", help="also write NAME_flow.npy, float32 (2, H, W), x then y, px")
    p.add_argument("--save-intermediate", action="store_true", help="also write NAME_deblurred.png (Î_tilt)")
    p.set_defaults(func=run)


def _iter_video(path: Path):
    """Yield (index, (3,H,W) float tensor) for each frame of a video file."""
    try:
        import imageio.v3 as iio
    except ImportError as exc:
        raise D2TurbError(f"{path}: reading video needs imageio; {VIDEO_HINT}") from exc
    from d2turb.restore import frame_to_tensor

    try:
        plugin = "pillow" if path.suffix.lower() == ".gif" else "pyav"  # pyav comes with the video extra
        for i, frame in enumerate(iio.imiter(path, plugin=plugin)):
            yield i, frame_to_tensor(frame)
    except (OSError, ValueError, RuntimeError, ImportError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else exc.__class__.__name__
        raise D2TurbError(f"{path}: cannot read video ({first}); {VIDEO_HINT}") from exc


def split_inputs(inputs: list[str]) -> tuple[list[Path], list[Path]]:
    """(image files, video files) named on the command line; output names must be unique."""
    from d2turb.io import expand_inputs

    images, videos = [], []
    for item in inputs:
        p = Path(item)
        if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES:
            videos.append(p)
        else:
            images.extend(expand_inputs([item]))
    stems = [p.stem for p in images + videos]
    clash = sorted({s for s in stems if stems.count(s) > 1})
    if clash:
        raise D2TurbError(f"several inputs would write the same output name: {', '.join(clash)}")
    return images, videos


def run(args) -> int:
    import numpy as np
    import torch
    from tqdm import tqdm

    from d2turb.io import read_image, write_image, write_npy
    from d2turb.restore import Restorer

    images, videos = split_inputs(args.inputs)
    restorer = Restorer(args.weights, device=args.device, tile=args.tile, overlap=args.overlap, progress=True)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)

    def save(stem: str, image: torch.Tensor) -> None:
        details = restorer.restore_with_details(image)
        write_image(out_dir / f"{stem}_restored.png", details["restored"])
        if args.save_flow:
            write_npy(out_dir / f"{stem}_flow.npy", details["flow"].numpy().astype(np.float32))
        if args.save_intermediate:
            write_image(out_dir / f"{stem}_deblurred.png", details["deblurred"])

    count = 0
    for path in tqdm(images, desc="restore", unit="img", disable=len(images) < 2):
        save(path.stem, read_image(path))
        count += 1
    for video in videos:
        for i, frame in tqdm(_iter_video(video), desc=video.name, unit="frame"):
            save(f"{video.stem}_{i:06d}", frame)
            count += 1
    print(f"restored {count} image(s) with {restorer.name} into {out_dir}")
    return 0
