"""`d2turb evaluate`: metrics on a synthetic test set (--data, --clips: with ground truth), on real images (--real) or
real clips (--real-clips)."""

from __future__ import annotations

import os
import sys

from d2turb.commands.common import add_device_arg, add_fail_fast_arg, add_max_pixels_arg
from d2turb.defaults import (
    CLIP_FUSIONS,
    DEFAULT_FUSION,
    DEFAULT_REAL_CLIP_FRAMES,
    DEFAULT_TEMPORAL,
    MEASURED_TEMPORAL,
)
from d2turb.errors import D2TurbError, print_error, summary


def register(sub):
    p = sub.add_parser(
        "evaluate",
        help="evaluate restoration models (PSNR/SSIM/LPIPS with ground truth, NIQE/PIQE without)",
        description="With --data: full-reference metrics of each model on a synthetic dataset. With --real: "
        "no-reference metrics (NIQE, PIQE) of real images, after restoring them with each --weights "
        "model ('input' = unrestored). With --clips: clip restoration per bin (PSNR/SSIM, offset-removed, CW-SSIM). "
        "With --real-clips: the real clips report (contact sheets, NIQE/PIQE, residual motion, blind estimate). "
        "Writes OUT/results.json and OUT/results.md. Unreadable images (samples, clips) are reported, skipped and "
        "listed in results.json; the exit status is then 1.",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--data", metavar="DATASET_DIR", help="synthetic dataset folder (from make_dataset)")
    src.add_argument("--real", metavar="DIR", help="folder of real degraded images (no ground truth)")
    src.add_argument(
        "--clips",
        metavar="DATASET_DIR",
        help="sequence dataset (make-dataset --frames N): clip restoration per bin (docs/clips.md)",
    )
    src.add_argument(
        "--real-clips",
        metavar="DIR",
        help="folder of real clips (videos, folders of frames): each restored once with the defaults of restore "
        "--temporal; contact sheets, blind estimate, residual motion, NIQE/PIQE of input | mean fusion | default "
        "(docs/clips.md)",
    )
    p.add_argument(
        "--temporal",
        type=int,
        default=None,
        metavar="N",
        help=f"with --clips: window (default {MEASURED_TEMPORAL}); with --real-clips: the restoration's window "
        f"(default {DEFAULT_TEMPORAL}, must be shorter than each clip)",
    )
    p.add_argument(
        "--max-frames",
        type=int,
        default=None,
        metavar="N",
        help=f"with --real-clips: frames read per clip, from its start (default {DEFAULT_REAL_CLIP_FRAMES})",
    )
    p.add_argument(
        "--lookahead",
        type=int,
        default=None,
        metavar="L",
        help="with --clips: windows that reach at most L frames ahead, as a stream's (restore -: N/2 - 1); default "
        "centred, as a file's",
    )
    p.add_argument(
        "--preset",
        default="balanced",
        choices=["fast", "balanced", "medium", "fine"],
        help="with --clips: the preset of restore --temporal (default balanced; fast: the live preset)",
    )
    p.add_argument("--fusion", default=DEFAULT_FUSION, choices=CLIP_FUSIONS, help="with --clips: fusion (default mean)")
    p.add_argument(
        "--deblur",
        nargs="+",
        default=["physics"],
        metavar="D",
        help="with --clips: deblur options after fusion: physics (at each clip's true D/r0 and optics), blind (the "
        "default of restore --temporal) and/or weights (default physics)",
    )
    p.add_argument(
        "--recursive",
        action="store_true",
        help="with --real: also the images in DIR's sub-folders (e.g. one folder per clip), with means per folder",
    )
    p.add_argument(
        "--weights",
        nargs="+",
        metavar="W",
        help="models to evaluate: .safetensors paths or names, and/or 'input' (identity baseline); "
        "with --real the default is 'input' only",
    )
    p.add_argument(
        "--metrics",
        default=None,
        help="comma-separated metrics (default: psnr,ssim,lpips with --data, LPIPS skipped with a note "
        "when its weights are missing; --data also offers epe (flow end-point error, px) and psnr_tilt "
        "(deblurred vs I_tilt); niqe,piqe with --real)",
    )
    p.add_argument("--out", required=True, help="output folder")
    add_device_arg(p)
    p.add_argument("--max-samples", type=int, default=None, help="evaluate at most this many images")
    p.add_argument(
        "--lpips-weights",
        metavar="FILE",
        help="LPIPS v0.1 linear-layer weights (alex.pth / vgg.pth); "
        "else $D2TURB_LPIPS_WEIGHTS or $D2TURB_CACHE_DIR (~/.cache/d2turb/)",
    )
    p.add_argument(
        "--lpips-backbone",
        metavar="FILE",
        help="torchvision AlexNet/VGG16 weights; else $D2TURB_LPIPS_BACKBONE or ~/.cache/d2turb/",
    )
    p.add_argument(
        "--musiq-weights",
        metavar="FILE",
        help="MUSIQ checkpoint (IQA-PyTorch .pth or .safetensors); else "
        "$D2TURB_MUSIQ_WEIGHTS or ~/.cache/d2turb/musiq/",
    )
    add_max_pixels_arg(p)
    add_fail_fast_arg(p)
    p.set_defaults(func=run)


def run(args):
    # lazy: see d2turb.commands
    from d2turb.device import resolve_device
    from d2turb.io import check_output_dir, remove_stale_temp_files

    if args.max_samples is not None and args.max_samples < 1:
        raise D2TurbError(f"--max-samples must be at least 1, got {args.max_samples}")
    if args.data and not args.weights:
        raise D2TurbError("--data needs --weights (model files/names, or 'input' for the unrestored baseline)")
    if args.recursive and not args.real:
        raise D2TurbError("--recursive goes with --real (a synthetic dataset is one folder)")
    if args.max_frames is not None and not args.real_clips:
        raise D2TurbError("--max-frames goes with --real-clips")
    if args.real_clips:
        return _run_real_clips(args)
    device = str(resolve_device(args.device))
    remove_stale_temp_files(check_output_dir(args.out) / "grids", recursive=True)  # grids/<folder>/ with --recursive
    if args.clips:
        # lazy: the clip pipeline (OpenCV) loads only for --clips
        from d2turb.eval.clips import evaluate_clips, markdown

        results = evaluate_clips(
            args.clips,
            args.out,
            deblur=args.deblur,
            temporal=MEASURED_TEMPORAL if args.temporal is None else args.temporal,
            preset=args.preset,
            fusion=args.fusion,
            max_samples=args.max_samples,
            device=device,
            lookahead=args.lookahead,
        )
        print(markdown(results))
        print(f"wrote {os.path.join(args.out, 'results.json')}")
        return 0
    if args.real:
        # lazy: the no-reference metrics (scipy, MUSIQ) load only for --real
        from d2turb.eval.real import evaluate_real, parse_metrics

        results = evaluate_real(
            args.real,
            parse_metrics(args.metrics or "niqe,piqe"),
            args.out,
            weights=args.weights,
            device=device,
            max_samples=args.max_samples,
            musiq_weights=args.musiq_weights,
            fail_fast=args.fail_fast,
            on_skip=print_error,
            recursive=args.recursive,
            on_note=lambda message: print(f"note: {message}", file=sys.stderr),
        )
        for model, scores in results["models"].items():
            print(model + ": " + ", ".join(f"{m} {v['mean']:.4f}" for m, v in scores.items()))
        for folder, entry in results.get("folders", {}).items():
            count = len(entry["images"])
            for model, means in entry["models"].items():
                scores = ", ".join(f"{m} {v:.4f}" for m, v in means.items())
                print(f"{folder} ({count} image{'s' * (count != 1)}), {model}: {scores}")
        total = len(results["images"]) + len(results["skipped"])
    else:
        # lazy: the synthetic evaluator (datasets, models) loads only for --data
        from d2turb.eval.real import parse_metrics
        from d2turb.eval.synthetic import evaluate_synthetic

        # metrics=None: the default set, where missing LPIPS weights only drop the LPIPS column with a note
        metrics = tuple(parse_metrics(args.metrics)) if args.metrics else None
        results = evaluate_synthetic(
            args.weights,
            args.data,
            args.out,
            device=device,
            metrics=metrics,
            max_samples=args.max_samples,
            lpips_weights=args.lpips_weights,
            lpips_backbone=args.lpips_backbone,
            fail_fast=args.fail_fast,
            on_skip=print_error,
        )
        results = results or {}
        total = results.get("samples_evaluated", 0) + len(results.get("skipped", []))
    print(f"wrote {os.path.join(args.out, 'results.json')}")
    return summary("evaluate", total, len(results.get("skipped", [])))


def _run_real_clips(args) -> int:
    """``--real-clips DIR``: the real clips report (d2turb.eval.real_clips)."""
    # lazy: the clip pipeline (OpenCV) and the no-reference metrics load only here
    from d2turb.eval.real_clip_markdown import markdown
    from d2turb.eval.real_clips import evaluate_real_clips
    from d2turb.io import check_output_dir, remove_stale_temp_files

    out = check_output_dir(args.out)
    remove_stale_temp_files(out / "sheets", recursive=True)  # sheets/<folder>/ for clips in sub-folders
    results = evaluate_real_clips(
        args.real_clips,
        out,
        temporal=args.temporal,
        max_frames=DEFAULT_REAL_CLIP_FRAMES if args.max_frames is None else args.max_frames,
        fail_fast=args.fail_fast,
        on_skip=print_error,
    )
    print(markdown(results))
    print(f"wrote {os.path.join(args.out, 'results.json')}")
    return summary("evaluate", len(results["clips"]) + len(results["skipped"]), len(results["skipped"]))
