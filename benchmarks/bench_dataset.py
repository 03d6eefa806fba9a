"""make-dataset throughput: pairs/s at 256² on CPU (or --device), JSON on stdout.

    python3 benchmarks/bench_dataset.py [--pairs 16] [--patch 256] [--threads 2] [--depth prior] [--clean DIR ...]

Without --clean it writes a few built-in scikit-image samples (upscaled to 512 px) to a temp folder.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import torch


def sample_images(folder: Path) -> list[str]:
    from PIL import Image
    from skimage import data

    for name in ("astronaut", "coffee", "chelsea", "rocket"):
        img = Image.fromarray(getattr(data, name)()).convert("RGB")
        img.resize((512, round(512 * img.height / img.width))).save(folder / f"{name}.png")
    return [str(folder)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=16)
    ap.add_argument("--patch", type=int, default=256)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--depth", default="prior")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--clean", nargs="*")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    from d2turb.data.generate import DatasetConfig, generate_dataset

    with tempfile.TemporaryDirectory() as tmp:
        clean = args.clean or sample_images(Path(tmp))
        cfg = DatasetConfig(
            clean=clean,
            out=str(Path(tmp) / "ds"),
            pairs=args.pairs,
            patch=args.patch,
            split="train",
            depth=args.depth,
            seed=0,
            batch=args.batch,
            device=args.device,
        )
        start = time.perf_counter()
        stats = generate_dataset(cfg, progress=False)
        total = time.perf_counter() - start
    result = {
        "benchmark": "make-dataset",
        "pairs": args.pairs,
        "patch": args.patch,
        "batch": args.batch,
        "depth": args.depth,
        "device": stats["device"],
        "threads": torch.get_num_threads(),
        "seconds": round(total, 3),
        "pairs_per_s": round(args.pairs / total, 3),
        "generation_pairs_per_s": round(stats["pairs_per_s"], 3),
        "torch": torch.__version__,
        "python": platform.python_version(),
        "date": time.strftime("%Y-%m-%d"),
    }
    if args.device.startswith("cuda") or (args.device == "auto" and torch.cuda.is_available()):
        result["gpu"] = torch.cuda.get_device_name(0)
    json.dump(result, sys.stdout)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
