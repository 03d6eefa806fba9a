"""`d2turb simulate` over a folder against the in-process batched simulator, per image, measured in one run.

    python3 benchmarks/bench_cli_sim.py [--images 64] [--size 256] [--rounds 5] [--threads 2]
                                        [--baseline-src /path/to/older/src] [--json FILE]

Each round, back to back on the same folder of natural-image crops (scikit-image samples, PNG):
1. ``sim``: a new simulator in this process over the images, already in memory (batch 8; its set-up on the
   first call is counted, as in the command);
2. ``cli``: ``d2turb.cli.main(["simulate", FOLDER, ...])`` in this process — the console command's code path
   (reading, simulator construction and first-call set-up, simulation, background writing), without the
   interpreter start-up;
3. ``child``: the same command in a fresh child process, which runs it twice: over the first batch of images
   (its first call pays the imports, caches and set-up: ``first_call_s``), then over the whole folder (the
   per-image figures); ``process_s`` is the child's wall time in all, interpreter start-up included;
4. ``baseline`` (with ``--baseline-src``): the same child run with another source tree (e.g. the version
   before a change).
Per-image wall and CPU times (CPU = all threads of the process; on a machine shared with other jobs the
scheduler shares cores per thread, which skews wall times of multi-threaded steps). Ratios are taken within
each round, then the median over rounds. Prints one JSON object (and writes it to --json FILE), with the
PNG writing cost (conversion, encoding, atomic file) per zlib level.
"""

from __future__ import annotations

import argparse
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
    """(wall, CPU) seconds per image of a new Simulator over the images (already in memory), batches of
    ``batch``: the simulator's set-up (field spectra on its first call) is counted, as in the command."""
    from d2turb.io import read_image
    from d2turb.sim import Simulator, TurbulenceParams

    images = torch.stack([read_image(p) for p in paths])
    start, cpu = time.perf_counter(), time.process_time()
    sim = Simulator(TurbulenceParams(dr0=3.0))
    gen = torch.Generator().manual_seed(0)
    for i in range(0, len(images), batch):
        sim(images[i : i + batch], generator=gen)
    return (time.perf_counter() - start) / len(images), (time.process_time() - cpu) / len(images)


CHILD = """
import contextlib, json, os, sys, time
from d2turb.cli import main
warm, folder, out, extra = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4:]
result = {}
with open(os.devnull, "w") as null, contextlib.redirect_stdout(null):
    for key, src in (("first", warm), ("steady", folder)):
        start, cpu = time.perf_counter(), time.process_time()
        rc = main(["simulate", src, "--out", os.path.join(out, key), "--dr0", "3", *extra])
        result[key] = {"rc": rc, "s": time.perf_counter() - start, "cpu_s": time.process_time() - cpu}
print(json.dumps(result))
"""


def time_cli(src: Path, warm: Path, folder: Path, out: Path, threads: int, extra: list[str]) -> dict:
    """A child process runs the command twice, over ``warm`` (its first call: imports, caches, set-up) and then
    over ``folder``: {"first"|"steady": {"s", "cpu_s"}} inside ``d2turb.cli.main`` and "process_s", the child's
    wall time in all (interpreter start-up included). CPU = all threads of the process."""
    env = {**os.environ, "PYTHONPATH": str(src), "OMP_NUM_THREADS": str(threads)}
    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-c", CHILD, str(warm), str(folder), str(out), *extra],
        env=env,
        capture_output=True,
        text=True,
    )
    result = json.loads(done.stdout.strip().splitlines()[-1]) if done.returncode == 0 else {}
    if not result or any(v["rc"] != 0 for v in result.values()):
        raise RuntimeError(f"simulate failed: {done.stderr}")
    return {**result, "process_s": time.perf_counter() - start}


def png_costs(size: int) -> dict:
    """ms to write one size² RGB output (a simulated natural image) per zlib level with the command's own
    writer (``d2turb.io.write_image``: conversion, PNG encoding, atomic file), and the file's size."""
    from d2turb.io import read_image, write_image
    from d2turb.sim import Simulator, TurbulenceParams

    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        image = read_image(make_images(Path(tmp), 1, size)[0])
        turb = Simulator(TurbulenceParams(dr0=3.0))(image[None], generator=torch.Generator().manual_seed(0)).turb[0]
        for level in (1, 6, 9):
            path, times = Path(tmp) / f"level{level}.png", []
            for _ in range(10):
                start = time.perf_counter()
                write_image(path, turb, level)
                times.append(time.perf_counter() - start)
            out[str(level)] = {"ms": round(1000 * statistics.median(times), 2), "bytes": path.stat().st_size}
    return out


def time_main(folder: Path, out: Path, batch: int) -> tuple[float, float]:
    """(wall, CPU) seconds of ``d2turb.cli.main`` simulate over ``folder`` in this process."""
    import contextlib

    from d2turb.cli import main as cli_main

    with open(os.devnull, "w") as null, contextlib.redirect_stdout(null):
        start, cpu = time.perf_counter(), time.process_time()
        rc = cli_main(["simulate", str(folder), "--out", str(out), "--dr0", "3", "--batch", str(batch)])
        wall, cpu = time.perf_counter() - start, time.process_time() - cpu
    if rc != 0:
        raise RuntimeError("simulate failed")
    return wall, cpu


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=64)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--baseline-src", type=Path, default=None, help="another source tree's src/ to time too")
    ap.add_argument("--json", default=None, metavar="FILE")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    n = args.images
    rounds = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        paths = make_images(tmp / "in", n, args.size)
        (tmp / "warm").mkdir()
        for p in paths[: args.batch]:
            (tmp / "warm" / p.name).symlink_to(p)
        for r in range(args.rounds):
            row = {"load_avg_1min": round(os.getloadavg()[0], 2)}
            wall, cpu = time_in_process(paths, args.batch)
            row["sim"] = {"wall_s_per_image": wall, "cpu_s_per_image": cpu}
            wall, cpu = time_main(tmp / "in", tmp / f"cli-{r}", args.batch)
            row["cli"] = {"wall_s_per_image": wall / n, "cpu_s_per_image": cpu / n}
            children = {"child": (SRC, ["--batch", str(args.batch)])}
            if args.baseline_src:
                children["baseline"] = (args.baseline_src, [])
            for name, (src, extra) in children.items():
                t = time_cli(src, tmp / "warm", tmp / "in", tmp / f"{name}-{r}", args.threads, extra)
                row[name] = {
                    "wall_s_per_image": t["steady"]["s"] / n,
                    "cpu_s_per_image": t["steady"]["cpu_s"] / n,
                    "first_call_s": t["first"]["s"],
                    "process_s": t["process_s"],
                }
            rounds.append(row)

    def med(values):
        return round(statistics.median(values), 3)

    summary = {
        "sim_ms_per_image": med(1000 * r["sim"]["wall_s_per_image"] for r in rounds),
        "sim_cpu_ms_per_image": med(1000 * r["sim"]["cpu_s_per_image"] for r in rounds),
    }
    for name in [k for k in ("cli", "child", "baseline") if k in rounds[0]]:
        entry = {
            "ms_per_image": med(1000 * r[name]["wall_s_per_image"] for r in rounds),
            "cpu_ms_per_image": med(1000 * r[name]["cpu_s_per_image"] for r in rounds),
            "ratio_to_sim": med(r[name]["wall_s_per_image"] / r["sim"]["wall_s_per_image"] for r in rounds),
            "cpu_ratio_to_sim": med(r[name]["cpu_s_per_image"] / r["sim"]["cpu_s_per_image"] for r in rounds),
        }
        if "first_call_s" in rounds[0][name]:
            entry["first_call_s"] = med(r[name]["first_call_s"] for r in rounds)  # over args.batch images
            entry["process_s"] = med(r[name]["process_s"] for r in rounds)
        summary[name] = entry
    report = {
        "benchmark": "cli_sim",
        "size": args.size,
        "batch": args.batch,
        "images": n,
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
