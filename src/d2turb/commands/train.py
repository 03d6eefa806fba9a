"""`d2turb train`: train a model from a YAML config (single process, or DDP under torchrun)."""

from __future__ import annotations

import os


def register(sub):
    p = sub.add_parser(
        "train",
        help="train a restoration model from a YAML config",
        description="Train from a YAML config (see configs/ and docs/training.md). Multi-GPU: "
        "torchrun --nproc_per_node N -m d2turb train ... (total batch split across processes). "
        "An existing RUN_DIR/last.pt is resumed automatically.",
    )
    p.add_argument("--config", required=True, metavar="YAML", help="training config file")
    p.add_argument("--out", metavar="RUN_DIR", help="run folder (default: runs/<config name>)")
    p.add_argument("--resume", action="store_true", help="require RUN_DIR/last.pt and continue from it")
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config value, e.g. --set train.iterations=100 (repeatable; value parsed as YAML)",
    )
    p.set_defaults(func=run)


def run(args):
    from d2turb.train import Trainer, load_config

    cfg = load_config(args.config, args.overrides)
    out = args.out or os.path.join("runs", os.path.splitext(os.path.basename(args.config))[0])
    trainer = Trainer(cfg, out, resume=args.resume)
    try:
        summary = trainer.fit()
    finally:
        trainer.close()
    if trainer.is_main:
        best = f", best val PSNR {summary['best_psnr']:.3f} dB" if summary["best_psnr"] > -float("inf") else ""
        print(
            f"trained {summary['iteration']}/{summary['total']} iterations, last loss {summary['loss']:.5f}{best}; "
            f"wrote {out}"
        )
    return 0
