"""Turbulent-sequence throughput and memory (issue 14).

    python3 benchmarks/bench_video.py [--json FILE] [--sizes 256 512] [--frames 48] [--threads 2]
                                      [--rss 64 512] [--no-cuda]

1. ``Simulator.sequence`` frames/s on one RGB clip (batch 1) at each size, on CPU (``--threads``) and on
   CUDA when present, after one warm-up frame; the single-frame simulator on the same image for reference.
   CPU time per frame (all threads) is recorded too: unlike wall time it hardly depends on other jobs.
2. ``d2turb simulate-video`` on a 256² image for each ``--rss`` frame count, in a fresh process: wall
   time (PNG per frame + mp4) and peak RSS, and the mp4 decoded again (frame count).
Prints one JSON object (and writes it to --json FILE). The machine's load average is recorded.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from d2turb.io import write_json
from d2turb.sim import Simulator, TurbulenceParams

CHILD = """
import resource, sys, time
from d2turb.cli import main
t = time.perf_counter()
rc = main(sys.argv[1:])
print("RESULT", rc, time.perf_counter() - t, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""


def sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def throughput(device: str, size: int, frames: int, dr0: float) -> dict:
    sim = Simulator(TurbulenceParams(dr0=dr0), device=device)
    img = torch.rand(1, 3, size, size, device=device)
    gen = torch.Generator().manual_seed(0)
    seq = sim.sequence(img, frames=frames + 1, fps=30.0, wind=2.0, wind_dir=20.0, generator=gen)
    next(seq)  # warm-up: spectra, plans, optics
    sync(device)
    start, cpu = time.perf_counter(), time.process_time()
    for _ in seq:
        pass
    sync(device)
    seq_s, seq_cpu = time.perf_counter() - start, time.process_time() - cpu
    sim(img, generator=gen)
    sync(device)
    n_still = max(1, frames // 4)
    start, cpu = time.perf_counter(), time.process_time()
    for _ in range(n_still):
        sim(img, generator=gen)
    sync(device)
    still_s, still_cpu = time.perf_counter() - start, time.process_time() - cpu
    return {
        "device": device,
        "size": size,
        "frames": frames,
        "frames_per_s": round(frames / seq_s, 2),
        "ms_per_frame": round(1000 * seq_s / frames, 1),
        "cpu_ms_per_frame": round(1000 * seq_cpu / frames, 1),  # all threads; robust to other jobs' load
        "still_images_per_s_batch1": round(n_still / still_s, 2),
        "still_cpu_ms_per_image": round(1000 * still_cpu / n_still, 1),
    }


def cli_run(frames: int, size: int, threads: int) -> dict:
    from PIL import Image
    from skimage import data, transform

    with tempfile.TemporaryDirectory() as tmp:
        img = transform.resize(data.astronaut(), (size, size), anti_aliasing=True)
        Image.fromarray((img * 255).round().astype("uint8")).save(Path(tmp) / "in.png")
        out = Path(tmp) / "out"
        args = ["simulate-video", str(Path(tmp) / "in.png"), "--out", str(out), "--frames", str(frames)]
        env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
        proc = subprocess.run(
            [sys.executable, "-c", CHILD, *args, "--wind", "2"], env=env, capture_output=True, text=True
        )
        line = [x for x in proc.stdout.splitlines() if x.startswith("RESULT")]
        if proc.returncode != 0 or not line:
            raise RuntimeError(proc.stderr[-2000:])
        _, rc, seconds, rss_kb = line[-1].split()
        decoded = None
        try:
            import imageio.v3 as iio

            decoded = int(iio.improps(out / "turb.mp4", plugin="pyav").shape[0])
        except ImportError:
            pass
        return {
            "frames": frames,
            "size": size,
            "seconds": round(float(seconds), 2),
            "frames_per_s": round(frames / float(seconds), 2),
            "peak_rss_mib": round(int(rss_kb) / 1024, 1),
            "mp4_frames_decoded": decoded,
        }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default=None, metavar="FILE")
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--dr0", type=float, default=3.0)
    ap.add_argument("--rss", type=int, nargs="*", default=[64, 512], help="frame counts for the CLI memory run")
    ap.add_argument("--no-cuda", action="store_true")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() and not args.no_cuda else [])
    load_before = os.getloadavg()
    results = [throughput(d, s, args.frames, args.dr0) for d in devices for s in args.sizes]
    cli = [cli_run(n, 256, args.threads) for n in args.rss]
    report = {
        "benchmark": "video",
        "dr0": args.dr0,
        "wind_m_s": 2.0,
        "fps": 30.0,
        "cpu_threads": args.threads,
        "torch": torch.__version__,
        "machine": platform.processor() or platform.machine(),
        "cuda_device": torch.cuda.get_device_name(0) if "cuda" in devices else None,
        "load_average_before_after": [round(load_before[0], 2), round(os.getloadavg()[0], 2)],
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "sequence": results,
        "simulate_video_cli": cli,
    }
    if len(cli) >= 2:
        report["rss_ratio_last_first"] = round(cli[-1]["peak_rss_mib"] / cli[0]["peak_rss_mib"], 3)
    text = json.dumps(report, indent=2)
    print(text)
    if args.json:
        write_json(args.json, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
