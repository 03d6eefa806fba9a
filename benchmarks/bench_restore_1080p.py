"""Time to restore one 1920×1080 frame with the recommended shipped model (issue 24: ≤ 10 s on 2 CPU cores).

    python3 benchmarks/bench_restore_1080p.py [--threads 2] [--repeats 3] [--weights NAME|FILE] [--json FILE]
    python3 benchmarks/bench_restore_1080p.py --random nafnet   # same architecture, random weights (no file needed)

Two figures, both on a 1920×1080 photo (skimage's astronaut, mirrored and resized, as bench_restore.py):
* ``inprocess_s``: ``Restorer.restore`` of the frame, median of ``--repeats`` calls after one warm-up call, model
  already loaded (default tiles 512, overlap 64);
* ``cli_s``: ``python -m d2turb restore FRAME --out DIR`` in a child process with ``--threads`` OpenMP threads and no
  ``--weights`` (the recommended shipped model), wall time from start to exit: interpreter start-up, imports,
  model loading, reading, restoration and writing the PNG. Skipped with ``--random`` or ``--weights``.
Prints one JSON object (and writes it to ``--json FILE``).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def make_photo(path: Path, width: int, height: int) -> None:
    import numpy as np
    from PIL import Image
    from skimage import data

    tile = np.concatenate([data.astronaut(), data.astronaut()[:, ::-1]], axis=1)
    Image.fromarray(np.ascontiguousarray(tile)).resize((width, height), Image.BICUBIC).save(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--tile", type=int, default=512)
    ap.add_argument("--overlap", type=int, default=64)
    ap.add_argument("--weights", help="weights name or file (default: the recommended shipped model)")
    ap.add_argument("--random", metavar="MODEL", help="time a randomly initialised registered model instead")
    ap.add_argument("--json", help="also write the JSON here")
    args = ap.parse_args()

    import torch

    from d2turb.io import read_image
    from d2turb.models import count_parameters, create_model
    from d2turb.models.hub import RECOMMENDED_WEIGHTS
    from d2turb.restore import Restorer

    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        frame = Path(tmp) / "frame.png"
        make_photo(frame, args.width, args.height)
        image = read_image(frame)
        if args.random:
            torch.manual_seed(0)
            weights, label = create_model(args.random).eval(), f"random {args.random}"
        else:
            weights = args.weights
            label = args.weights or RECOMMENDED_WEIGHTS
        restorer = Restorer(weights, tile=args.tile, overlap=args.overlap)
        restorer.restore(image)  # warm-up
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            restorer.restore(image)
            times.append(time.perf_counter() - t0)
        cli = None
        if not args.random and not args.weights:
            env = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
            t0 = time.perf_counter()
            subprocess.run(
                [sys.executable, "-m", "d2turb", "restore", str(frame), "--out", str(Path(tmp) / "out")],
                check=True,
                env=env,
                capture_output=True,
            )
            cli = time.perf_counter() - t0
    result = {
        "benchmark": "restore_1080p",
        "model": label,
        "params": count_parameters(restorer.model),
        "size": [args.width, args.height],
        "tile": args.tile,
        "overlap": args.overlap,
        "threads": args.threads,
        "inprocess_s": statistics.median(times),
        "inprocess_all_s": times,
        "cli_s": cli,
        "target_s": 10.0,
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}",
        "load_average": os.getloadavg(),
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }
    text = json.dumps(result, indent=2)
    print(text)
    if args.json:
        Path(args.json).write_text(text + "\n")


if __name__ == "__main__":
    main()
