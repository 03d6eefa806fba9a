"""Peak memory and time of `d2turb restore` on a large image (Acceptance 2: 4000x3000 on CPU within 8 GB).

Writes a W x H test photo (the astronaut sample, tiled and resized), saves a randomly initialised model of the
given config (default: the CPU preset d2turb_lite = d2turb with the NAFNet backbone) with a nonzero flow head,
then runs `python -m d2turb restore` in a child process and reports the child's peak RSS
(getrusage(RUSAGE_CHILDREN).ru_maxrss) and wall time as JSON.

    python3 benchmarks/bench_restore.py --width 4000 --height 3000 --threads 2
    python3 benchmarks/bench_restore.py --compare-untiled /path/to/photo.png   # tiled vs untiled accuracy
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from d2turb.defaults import DEFAULT_OVERLAP_PX, DEFAULT_TILE_PX


def torch_threads(n: int) -> None:
    import torch

    torch.set_num_threads(n)


def make_photo(path: Path, width: int, height: int) -> None:
    import numpy as np
    from PIL import Image
    from skimage import data

    tile = np.concatenate([data.astronaut(), data.astronaut()[:, ::-1]], axis=1)
    Image.fromarray(np.ascontiguousarray(tile)).resize((width, height), Image.BICUBIC).save(path, quality=92)


def make_weights(path: Path, name: str, cfg: dict) -> int:
    import torch

    from d2turb.models import count_parameters, create_model, save_pretrained

    torch.manual_seed(0)
    model = create_model(name, **cfg)
    torch.nn.init.normal_(model.rectifier.flow_head.weight, std=0.5)  # the warp moves pixels (a few px)
    save_pretrained(model, path)
    return count_parameters(model)


def compare_untiled(
    image_path: str | None, width: int, height: int, name: str, cfg: dict, tile: int, overlap: int
) -> dict:
    """Tiled vs untiled restoration of one image (in-process): mean/max |difference| and the gradient energy
    across tile edges relative to the untiled output (1.0 = no seam)."""
    import torch

    from d2turb.io import read_image
    from d2turb.models import create_model
    from d2turb.restore import Restorer, tile_starts

    torch.manual_seed(0)
    model = create_model(name, **cfg).eval()
    torch.nn.init.normal_(model.rectifier.flow_head.weight, std=0.5)
    if image_path:
        image = read_image(image_path)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            make_photo(Path(tmp) / "p.jpg", width, height)
            image = read_image(Path(tmp) / "p.jpg")
    h, w = image.shape[-2:]
    untiled = Restorer(model, tile=max(h, w)).restore_with_details(image)
    tiled = Restorer(model, tile=tile, overlap=overlap).restore_with_details(image)

    def edges(length):
        return sorted({e for s in tile_starts(length, tile, overlap) for e in (s, s + tile) if 0 < e < length})

    out = {
        "image": image_path or f"astronaut {width}x{height}",
        "size": f"{w}x{h}",
        "tile": tile,
        "overlap": overlap,
        "flow_abs_mean_px": round(float(untiled["bwd_flow_px"].abs().mean()), 3),
    }
    for key, label in (("restored", "restored"), ("bwd_flow_px", "flow")):  # labels as in earlier results
        d = (tiled[key] - untiled[key]).abs()
        cols, rows = [c - 1 for c in edges(w)], [r - 1 for r in edges(h)]
        ratio_x = float(
            tiled[key].diff(dim=-1).abs()[..., cols].mean() / untiled[key].diff(dim=-1).abs()[..., cols].mean()
        )
        ratio_y = float(
            tiled[key].diff(dim=-2).abs()[..., rows, :].mean() / untiled[key].diff(dim=-2).abs()[..., rows, :].mean()
        )
        out[label] = {
            "mad": float(d.mean()),
            "max": float(d.max()),
            "edge_gradient_ratio_x": round(ratio_x, 4),
            "edge_gradient_ratio_y": round(ratio_y, 4),
        }
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--width", type=int, default=4000)
    p.add_argument("--height", type=int, default=3000)
    p.add_argument("--model", default="d2turb_lite")
    p.add_argument("--config", help="model config as JSON (string or path to a .json file)")
    p.add_argument("--tile", type=int, default=DEFAULT_TILE_PX)
    p.add_argument("--overlap", type=int, default=DEFAULT_OVERLAP_PX)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--device", default="cpu")
    p.add_argument(
        "--compare-untiled",
        nargs="?",
        const="",
        metavar="IMAGE",
        help="instead: compare tiled with untiled restoration on IMAGE (default: the test photo)",
    )
    args = p.parse_args()
    from d2turb.commands.common import model_config  # no torch: the threads are set first

    config = model_config(args.config)
    torch_threads(args.threads)
    if args.compare_untiled is not None:
        r = compare_untiled(
            args.compare_untiled or None,
            args.width,
            args.height,
            args.model,
            config,
            args.tile,
            args.overlap,
        )
        r["date"] = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
        print(json.dumps(r))
        return
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        photo, weights = tmp / "photo.jpg", tmp / "model.safetensors"
        make_photo(photo, args.width, args.height)
        params = make_weights(weights, args.model, config)
        env = dict(os.environ, OMP_NUM_THREADS=str(args.threads), MKL_NUM_THREADS=str(args.threads))
        cmd = [
            sys.executable,
            "-m",
            "d2turb",
            "restore",
            str(photo),
            "--weights",
            str(weights),
            "--out",
            str(tmp / "out"),
            "--tile",
            str(args.tile),
            "--overlap",
            str(args.overlap),
            "--device",
            args.device,
            "--save-flow",
            "--save-intermediate",
        ]
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, env=env)
        wall = time.perf_counter() - t0
        peak_kib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss  # KiB on Linux
        outputs = sorted(f.name for f in (tmp / "out").iterdir())
    print(
        json.dumps(
            {
                "image": f"{args.width}x{args.height}",
                "model": args.model,
                "config": config,
                "parameters": params,
                "tile": args.tile,
                "overlap": args.overlap,
                "device": args.device,
                "threads": args.threads,
                "wall_s": round(wall, 1),
                "peak_rss_gib": round(peak_kib / 2**20, 3),
                "outputs": outputs,
                "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
                "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            }
        )
    )


if __name__ == "__main__":
    main()
