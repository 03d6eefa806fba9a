"""Training throughput (images/s) of ``d2turb.train.Trainer`` and the share of a step spent in data, synthesis and
forward/backward/optimiser, at a given model, patch, batch and device.

    python3 benchmarks/bench_train.py [--model d2turb_lite] [--patch 128] [--batch 4] [--device cpu|cuda]
        [--steps 10] [--warmup 2] [--pack DIR] [--amp bf16] [--channels-last] [--compile] [--ema 0.999]
        [--threads 2] [--json FILE]

Without ``--pack`` a small pack is made in a temporary folder from scikit-image's sample photographs, so the
script runs anywhere. Each step is timed in three parts, with a device synchronisation between them: ``data``
(crops from the in-memory pack, collated), ``synthesis`` (on-the-fly turbulence on the training device) and
``step`` (forward, loss, backward, Adam, EMA). Prints one JSON object (and writes it to --json FILE).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import torch

from d2turb.io import write_json
from d2turb.train import Trainer, load_config


def sample_pack(folder: Path, patch: int) -> Path:
    """A pack of four scikit-image sample photographs (train split), resized so the short side is ≥ 2·patch."""
    import numpy as np
    from PIL import Image
    from skimage import data

    from d2turb.data.pack import make_pack

    (folder / "clean" / "samples").mkdir(parents=True, exist_ok=True)
    for name in ("astronaut", "coffee", "chelsea", "rocket"):
        image = Image.fromarray(np.asarray(getattr(data, name)())[..., :3])
        scale = max(1.0, 2 * patch / min(image.size))
        image = image.resize((round(image.width * scale), round(image.height * scale)), Image.Resampling.BICUBIC)
        image.save(folder / "clean" / "samples" / f"{name}.png")
    return Path(make_pack([folder / "clean"], folder / "pack", patch=patch)["out"])


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def bench(args, pack: Path, run_dir: Path) -> dict:
    train = {"iterations": 10**6, "batch": args.batch, "device": args.device, "amp": args.amp}
    train.update(channels_last=args.channels_last, compile=args.compile, ema=args.ema)
    cfg = load_config(
        base={
            "model": {"name": args.model, **json.loads(args.model_cfg)},
            "data": {"pack": str(pack), "patch": args.patch, "on_the_fly": {"depth": args.depth}},
            "train": train,
            "loss": {"vgg": 0.0},
            "log": {"progress": False},
        }
    )
    built = time.perf_counter()
    trainer = Trainer(cfg, run_dir)
    setup_s = time.perf_counter() - built
    device = trainer.device

    def batches():
        while True:
            yield from trainer.data.loader

    stream = batches()
    totals = {"data": 0.0, "synthesis": 0.0, "step": 0.0}
    for i in range(args.warmup + args.steps):
        _sync(device)
        t0 = time.perf_counter()
        batch = next(stream)
        _sync(device)
        t1 = time.perf_counter()
        batch = trainer.data.to_device(batch)
        _sync(device)
        t2 = time.perf_counter()
        trainer.train_step(batch)
        _sync(device)
        t3 = time.perf_counter()
        if i >= args.warmup:
            for key, dt in (("data", t1 - t0), ("synthesis", t2 - t1), ("step", t3 - t2)):
                totals[key] += dt
    total = sum(totals.values())
    result = {
        "model": args.model,
        "parameters": sum(p.numel() for p in trainer.model.parameters()),
        "patch": args.patch,
        "batch": args.batch,
        "device": str(device),
        "amp": args.amp,
        "channels_last": args.channels_last,
        "compile": args.compile,
        "ema": args.ema,
        "depth": args.depth,
        "steps": args.steps,
        "setup_s": round(setup_s, 2),
        "ms_per_step": round(1000 * total / args.steps, 2),
        "images_per_s": round(args.steps * args.batch / total, 3),
        "share": {k: round(v / total, 4) for k, v in totals.items()},
    }
    if device.type == "cuda":
        result["peak_gpu_mib"] = round(torch.cuda.max_memory_allocated(device) / 2**20, 1)
    return result


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="d2turb_lite")
    ap.add_argument("--model-cfg", default="{}", help="create_model keyword arguments as JSON")
    ap.add_argument("--patch", type=int, default=128)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--device", default="cpu", help="cpu | cuda | auto")
    ap.add_argument("--steps", type=int, default=10, help="timed steps (after --warmup)")
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--pack", default=None, help="a make-pack folder (default: a temporary sample pack)")
    ap.add_argument("--depth", default="prior", help="none | prior")
    ap.add_argument("--amp", default=None, choices=[None, "bf16"])
    ap.add_argument("--channels-last", action="store_true")
    ap.add_argument("--compile", action="store_true")
    ap.add_argument("--ema", type=float, default=None)
    ap.add_argument("--threads", type=int, default=2, help="CPU threads (torch.set_num_threads)")
    ap.add_argument("--json", default=None, metavar="FILE")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        pack = Path(args.pack) if args.pack else sample_pack(Path(tmp), args.patch)
        result = bench(args, pack, Path(tmp) / "run")
    report = {
        "benchmark": "train",
        "torch": torch.__version__,
        "cpu_threads": args.threads,
        "machine": platform.processor() or platform.machine(),
        "cuda_device": torch.cuda.get_device_name(0) if result["device"].startswith("cuda") else None,
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "pack": args.pack or "scikit-image samples (temporary)",
        "result": result,
    }
    print(json.dumps(report, indent=2))
    if args.json:
        write_json(args.json, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
