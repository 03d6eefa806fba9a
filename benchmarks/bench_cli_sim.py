"""`d2turb simulate` over a folder against the in-process batched simulator, per image, measured in one run.

    python3 benchmarks/bench_cli_sim.py [--images 64] [--size 256] [--batch 8] [--rounds 5] [--threads 2]
                                        [--baseline-src /path/to/older/src] [--json FILE]

A fresh child process (``--threads`` torch/OpenMP threads) makes the folder of natural-image crops
(scikit-image samples, PNG), runs the command once over its first batch (``first_call_s``: the command's own
imports, caches and set-up) and then, ``--rounds`` times, back to back in the same process:
1. ``cli``: ``d2turb.cli.main(["simulate", FOLDER, ...])`` — the console command's code path (reading,
   simulator construction and first-call set-up, simulation, writing), without the interpreter start-up;
2. ``sim``: a new simulator over the same images, already in memory (batch ``--batch``; its set-up on the
   first call counted, as in the command);
and at the end ``own``: the command once more with the simulator replaced by a stored result (its own work:
reading, writing, bookkeeping).
Both in one process, alternating, so they share its state (allocator, caches) and the machine's moment; the
ratio is taken per round, then the median. With ``--baseline-src`` another child does the same with another
source tree (e.g. the version before a change). CPU = all threads of the process. Prints one JSON object
(and writes it to --json FILE), with the PNG writing cost (conversion, encoding, atomic file) per zlib level.
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
HERE = Path(__file__).resolve().parent


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


def measure(folder: Path, out: Path, batch: int, rounds: int) -> dict:
    """In this process: the command over the first batch, then ``rounds`` × (command, simulator) over the
    folder, then the command with a stored simulator result. Returns {"first_call_s", "rounds": [{"cli"|"sim":
    {"s", "cpu_s"}}], "own": {"s", "cpu_s"}} (whole folder)."""
    import contextlib
    import shutil
    from unittest import mock

    from d2turb.cli import main as cli_main
    from d2turb.io import read_image
    from d2turb.sim import Simulator, TurbulenceParams

    paths = sorted(folder.glob("*.png"))
    warm = folder.parent / "warm"
    warm.mkdir(exist_ok=True)
    for p in paths[:batch]:
        (warm / p.name).unlink(missing_ok=True)
        (warm / p.name).symlink_to(p)
    images = torch.stack([read_image(p) for p in paths])

    def command(src: Path) -> dict:
        shutil.rmtree(out, ignore_errors=True)
        with open(os.devnull, "w") as null, contextlib.redirect_stdout(null):
            start, cpu = time.perf_counter(), time.process_time()
            rc = cli_main(["simulate", str(src), "--out", str(out), "--dr0", "3", "--batch", str(batch)])
            result = {"s": time.perf_counter() - start, "cpu_s": time.process_time() - cpu}
        if rc != 0:
            raise RuntimeError("simulate failed")
        return result

    def simulator() -> dict:
        start, cpu = time.perf_counter(), time.process_time()
        sim = Simulator(TurbulenceParams(dr0=3.0))
        gen = torch.Generator().manual_seed(0)
        for i in range(0, len(images), batch):
            sim(images[i : i + batch], generator=gen)
        return {"s": time.perf_counter() - start, "cpu_s": time.process_time() - cpu}

    first = command(warm)["s"]
    result = {"first_call_s": first, "rounds": [{"cli": command(folder), "sim": simulator()} for _ in range(rounds)]}
    # the command's own work (reading, writing, bookkeeping): once more with the simulator replaced by a result
    stored = Simulator(TurbulenceParams(dr0=3.0))(images[:batch], generator=torch.Generator().manual_seed(0))
    with mock.patch.object(Simulator, "__call__", lambda self, image, **kwargs: stored):
        result["own"] = command(folder)
    return result


def run_child(src: Path, folder: Path, out: Path, args) -> dict:
    """:func:`measure` in a fresh process importing d2turb from ``src``; adds "process_s" (its wall time in all,
    interpreter start-up included)."""
    code = (
        f"import json, sys; sys.path.insert(0, {str(HERE)!r}); from pathlib import Path; import bench_cli_sim as b; "
        f"print(json.dumps(b.measure(Path({str(folder)!r}), Path({str(out)!r}), {args.batch}, {args.rounds})))"
    )
    env = {**os.environ, "PYTHONPATH": str(src), "OMP_NUM_THREADS": str(args.threads)}
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"child failed: {done.stderr}")
    return {**json.loads(done.stdout.strip().splitlines()[-1]), "process_s": time.perf_counter() - start}


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
    n, load = args.images, round(os.getloadavg()[0], 2)
    trees = {"current": SRC, **({"baseline": args.baseline_src} if args.baseline_src else {})}
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        make_images(tmp / "in", n, args.size)
        for name, src in trees.items():
            results[name] = run_child(src, tmp / "in", tmp / "out", args)

    def med(values):
        return round(statistics.median(values), 3)

    summary = {}
    for name, res in results.items():
        rounds = res["rounds"]
        summary[name] = {
            "cli_ms_per_image": med(1000 * r["cli"]["s"] / n for r in rounds),
            "sim_ms_per_image": med(1000 * r["sim"]["s"] / n for r in rounds),
            "cli_cpu_ms_per_image": med(1000 * r["cli"]["cpu_s"] / n for r in rounds),
            "sim_cpu_ms_per_image": med(1000 * r["sim"]["cpu_s"] / n for r in rounds),
            "ratio": med(r["cli"]["s"] / r["sim"]["s"] for r in rounds),
            "ratio_per_round": [round(r["cli"]["s"] / r["sim"]["s"], 3) for r in rounds],
            "cpu_ratio": med(r["cli"]["cpu_s"] / r["sim"]["cpu_s"] for r in rounds),
            "own_ms_per_image": round(1000 * res["own"]["s"] / n, 3),  # the simulator replaced by a stored result
            "own_cpu_ms_per_image": round(1000 * res["own"]["cpu_s"] / n, 3),
            "first_call_s": round(res["first_call_s"], 3),  # over args.batch images
            "process_s": round(res["process_s"], 3),
        }
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
        "load_avg_1min_at_start": load,
        "results": results,
    }
    text = json.dumps(report, indent=2)
    print(text)
    if args.json:
        Path(args.json).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
