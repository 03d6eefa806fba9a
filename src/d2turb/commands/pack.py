"""`d2turb make-pack`: the train and validation images of the fixed split as one compact training pack."""

from __future__ import annotations

import json


def register(sub):
    p = sub.add_parser(
        "make-pack",
        help="pack the train/validation clean images into one small folder (for GPU hosts)",
        description="Write a compact, self-describing training pack (JPEG images + pack.json manifest with "
        "sources, split and checksums) of the train and validation folders of the fixed split "
        "(d2turb.data.split; test folders are refused). Deterministic, atomic and restartable: rerun the "
        "same command after an interruption. Train with `data.pack: DIR` (docs/training.md).",
    )
    p.add_argument(
        "--clean",
        nargs="+",
        required=True,
        metavar="DIR",
        help="folders of clean images, or a parent of such folders (e.g. ../shared/data/clean; test folders skipped)",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="pack folder (e.g. packs/clean, git-ignored)")
    p.add_argument("--max-mib", type=float, default=40.0, help="size limit of the whole pack in MiB (default 40)")
    p.add_argument("--patch", type=int, default=256, help="downscaling keeps each short side >= this (default 256)")
    p.add_argument("--quality", type=int, default=90, help="JPEG quality (default 90)")
    p.add_argument("--max-side", type=int, default=None, help="largest long side to try (default: full size)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args):
    # lazy: see d2turb.commands
    from d2turb.data.pack import make_pack

    summary = make_pack(
        args.clean,
        args.out,
        max_mib=args.max_mib,
        patch=args.patch,
        quality=args.quality,
        max_side=args.max_side,
        progress=not args.no_progress,
    )
    print(json.dumps(summary, sort_keys=True))
    return 0
