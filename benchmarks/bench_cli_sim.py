"""`d2turb simulate` over a folder against the in-process batched simulator, per image, measured in one run.

    python3 benchmarks/bench_cli_sim.py [--images 16 64] [--size 256] [--rounds 3] [--threads 2]
                                        [--baseline-src /path/to/older/src] [--json FILE]

Each round, interleaved: the simulator in this process (batch 8, images in memory, after a warm-up call),
then the CLI in a child process on folders of SMALL and LARGE images. The CLI's per-image cost is the time
inside ``d2turb.cli.main`` over the LARGE folder divided by LARGE (reading, simulator construction and
first-call set-up, simulation, writing; interpreter start-up and imports excluded); the child's wall time
per image (start-up included) and the marginal wall cost (T(LARGE) - T(SMALL)) / (LARGE - SMALL) are
reported too, and CPU time (all threads) next to wall time: on a machine shared with other jobs the
scheduler shares the cores per thread, so wall times favour the process with more threads. Medians over
rounds. ``--baseline-src`` times another source tree's CLI (e.g. the version before a change) in the same
rounds. The images are natural-image crops (scikit-image samples), as PNG. Prints one JSON object (and
writes it to --json FILE), with the PNG encoding cost per zlib level.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

SRC = Path(__file__).resolve().parents[1] / "src"


def make_images(folder: Path, count: int, size: int) -> list[Path]:
    from PIL import Image
    from skimage import data, transform

    sources = [data.astronaut(), data.coffee(), data.chelsea(), data.rocket()]
    rng = np.random.default_rng(0)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(count):
        img = sources[i % len(sources)]
        scale = size / min(img.shape[:2]) * rng.uniform(1.0, 1.5)
        img = transform.resize(img, (round(img.shape[0] * scale), round(img.shape[1] * scale)), anti_aliasing=True)
        y, x = rng.integers(0, img.shape[0] - size + 1), rng.integers(0, img.shape[1] - size + 1)
        crop = np.round(img[y : y + size, x : x + size] * 255).astype(np.uint8)
        paths.append(folder / f"img{i:04d}.png")
        Image.fromarray(crop).save(paths[-1])
    return paths


def time_in_process(paths: list[Path], batch: int) -> tuple[float, float]:
    """(wall, CPU) seconds per image of Simulator alone (images already in memory), batches of ``batch``."""
    from d2turb.io import read_image
    from d2turb.sim import Simulator, TurbulenceParams

    images = torch.stack([read_image(p) for p in paths])
    sim = Simulator(TurbulenceParams(dr0=3.0))
    gen = torch.Generator().manual_seed(0)
    sim(images[:batch], generator=gen)  # warm-up: cached field spectra
    start, cpu = time.perf_counter(), time.process_time()
    for i in range(0, len(images), batch):
        sim(images[i : i + batch], generator=gen)
    return (time.perf_counter() - start) / len(images), (time.process_time() - cpu) / len(images)


CHILD = """
import contextlib, json, os, sys, time
from d2turb.cli import main
with open(os.devnull, "w") as null, contextlib.redirect_stdout(null):
    start, cpu = time.perf_counter(), time.process_time()
    rc = main(sys.argv[1:])
    elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu
print(json.dumps({"rc": rc, "main_s": elapsed, "main_cpu_s": cpu}))
"""


def time_cli(src: Path, folder: Path, out: Path, threads: int, extra: list[str]) -> tuple[float, float, float]:
    """(wall seconds of the child process, wall and CPU seconds inside ``d2turb.cli.main``) for simulate over
    ``folder``; CPU = all threads of the process."""
    env = {**os.environ, "PYTHONPATH": str(src), "OMP_NUM_THREADS": str(threads)}
    argv = ["simulate", str(folder), "--out", str(out), "--dr0", "3", *extra]
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", CHILD, *argv], env=env, check=True, capture_output=True, text=True)
    wall = time.perf_counter() - start
    result = json.loads(done.stdout.strip().splitlines()[-1])
    if result["rc"] != 0:
        raise RuntimeError(f"simulate failed: {done.stderr}")
    return wall, result["main_s"], result["main_cpu_s"]


def png_costs(size: int) -> dict:
    """ms to encode one size² RGB output (a simulated natural image) per zlib level, and its size."""
    from PIL import Image

    from d2turb.io import read_image
    from d2turb.sim import Simulator, TurbulenceParams

    with tempfile.TemporaryDirectory() as tmp:
        image = read_image(make_images(Path(tmp), 1, size)[0])
    turb = Simulator(TurbulenceParams(dr0=3.0))(image[None], generator=torch.Generator().manual_seed(0)).turb[0]
    pil = Image.fromarray(np.round(turb.clamp(0, 1).permute(1, 2, 0).numpy() * 255).astype(np.uint8))
    out = {}
    for level in (1, 6, 9):
        times, nbytes = [], 0
        for _ in range(10):
            buf = io.BytesIO()
            start = time.perf_counter()
            pil.save(buf, format="PNG", compress_level=level)
            times.append(time.perf_counter() - start)
            nbytes = buf.tell()
        out[str(level)] = {"ms": round(1000 * statistics.median(times), 2), "bytes": nbytes}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, nargs=2, default=[16, 64], metavar=("SMALL", "LARGE"))
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--baseline-src", type=Path, default=None, help="another source tree's src/ to time too")
    ap.add_argument("--json", default=None, metavar="FILE")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    small, large = args.images
    trees = {"this": SRC} | ({"baseline": args.baseline_src} if args.baseline_src else {})
    rounds = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        paths = make_images(tmp / "large", large, args.size)
        (tmp / "small").mkdir()
        for p in paths[:small]:
            (tmp / "small" / p.name).symlink_to(p)
        for r in range(args.rounds):
            wall, cpu = time_in_process(paths, args.batch)
            row = {
                "in_process_s_per_image": wall,
                "in_process_cpu_s_per_image": cpu,
                "load_avg_1min": os.getloadavg()[0],
            }
            for name, src in trees.items():
                extra = ["--batch", str(args.batch)] if name == "this" else []
                wall_small, _, _ = time_cli(src, tmp / "small", tmp / f"out-{name}-{r}-s", args.threads, extra)
                wall_large, main_large, cpu_large = time_cli(
                    src, tmp / "large", tmp / f"out-{name}-{r}-l", args.threads, extra
                )
                row[name] = {
                    "main_s": main_large,
                    "main_s_per_image": main_large / large,
                    "main_cpu_s_per_image": cpu_large / large,
                    "marginal_s_per_image": (wall_large - wall_small) / (large - small),
                    "wall_s_per_image": wall_large / large,
                }
            rounds.append(row)
    inproc = statistics.median(r["in_process_s_per_image"] for r in rounds)
    inproc_cpu = statistics.median(r["in_process_cpu_s_per_image"] for r in rounds)
    summary = {
        "in_process_ms_per_image": round(1000 * inproc, 1),
        "in_process_cpu_ms_per_image": round(1000 * inproc_cpu, 1),
    }
    for name in trees:
        per_image = statistics.median(r[name]["main_s_per_image"] for r in rounds)
        marginal = statistics.median(r[name]["marginal_s_per_image"] for r in rounds)
        wall = statistics.median(r[name]["wall_s_per_image"] for r in rounds)
        ratios = [r[name]["main_s_per_image"] / r["in_process_s_per_image"] for r in rounds]
        cpu = statistics.median(r[name]["main_cpu_s_per_image"] for r in rounds)
        cpu_ratios = [r[name]["main_cpu_s_per_image"] / r["in_process_cpu_s_per_image"] for r in rounds]
        summary[name] = {
            "cli_ms_per_image": round(1000 * per_image, 1),
            "ratio_cli_to_in_process": round(statistics.median(ratios), 3),
            "ratio_per_round": [round(x, 3) for x in ratios],
            "cli_cpu_ms_per_image": round(1000 * cpu, 1),
            "cpu_ratio_cli_to_in_process": round(statistics.median(cpu_ratios), 3),
            "cpu_ratio_per_round": [round(x, 3) for x in cpu_ratios],
            "cli_marginal_ms_per_image_from_wall": round(1000 * marginal, 1),
            "cli_wall_ms_per_image_incl_startup": round(1000 * wall, 1),
        }
    report = {
        "benchmark": "cli_sim",
        "size": args.size,
        "batch": args.batch,
        "images": [small, large],
        "threads": args.threads,
        "torch": torch.__version__,
        "machine": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "summary": summary,
        "png_encode": png_costs(args.size),
        "rounds": rounds,
    }
    text = json.dumps(report, indent=2)
    print(text)
    if args.json:
        Path(args.json).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
