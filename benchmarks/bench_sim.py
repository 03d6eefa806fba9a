"""Simulator throughput (images/s) at 256² and 1024² RGB on CPU (2 threads) and CUDA when present.

    python3 benchmarks/bench_sim.py [--json FILE] [--repeats N] [--threads T] [--dr0 X] [--sizes 256 1024]

Prints one JSON object to stdout (and writes it to --json FILE).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time

import torch

from d2turb.io import write_json
from d2turb.sim import Simulator, TurbulenceParams

BATCH = {256: 8, 512: 4, 1024: 2}


def bench(device: str, size: int, repeats: int, dr0: float) -> dict:
    batch = BATCH.get(size, 1)
    sim = Simulator(TurbulenceParams(dr0=dr0), device=device)
    img = torch.rand(batch, 3, size, size, device=device)
    gen = torch.Generator().manual_seed(0)
    sim(img, generator=gen)  # warm-up: builds the cached field spectra
    if device == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(repeats):
        sim(img, generator=gen)
    if device == "cuda":
        torch.cuda.synchronize()
    elapsed = time.perf_counter() - start
    n = batch * repeats
    return {
        "device": device,
        "size": size,
        "batch": batch,
        "images": n,
        "seconds": round(elapsed, 4),
        "images_per_s": round(n / elapsed, 2),
        "ms_per_image": round(1000 * elapsed / n, 2),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default=None, metavar="FILE")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--dr0", type=float, default=3.0)
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 1024])
    ap.add_argument("--no-cuda", action="store_true")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() and not args.no_cuda else [])
    results = [bench(d, s, args.repeats, args.dr0) for d in devices for s in args.sizes]
    report = {
        "benchmark": "sim",
        "dr0": args.dr0,
        "cpu_threads": args.threads,
        "torch": torch.__version__,
        "machine": platform.processor() or platform.machine(),
        "cuda_device": torch.cuda.get_device_name(0) if "cuda" in devices else None,
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "results": results,
    }
    text = json.dumps(report, indent=2)
    print(text)
    if args.json:
        write_json(args.json, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
