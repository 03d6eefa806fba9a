"""Resolution behaviour of the injection's channel attention: the authors' ASPI (logits Q·K / √(H·W)) vs our
``aspi_cosine`` variant (q, k L2-normalised over pixels, learned temperature), on the same content at 256²,
1024² and 1920×1080. Prints one JSON object (and writes it with --out).

    python3 benchmarks/bench_aspi_resolution.py --out benchmarks/aspi_resolution.json

Features: the image (skimage's astronaut, resized) through the authors' rectifier input projection (conv3×3+GELU,
32 channels) → F_shallow, and a fixed 1×1 embedding + tanh (96 channels) → F_guide; both modules are randomly
initialised with a fixed seed (no trained weights exist). Per resolution and variant:

* ``entropy``: mean entropy of an attention row, in nats, and ``entropy_rel`` = entropy / log(keys per row)
  (1 = uniform, 0 = one-hot);
* ``row_max``: mean of the largest probability of each row;
* ``attn_change``: mean |A − A(256²)| over the attention matrix;
* ``output_change``: ‖down(Δ) − Δ(256²)‖ / ‖Δ(256²)‖ for the attention term Δ (before γ), ``down`` = area
  resampling to 256².

The cosine variant is measured at temperatures 1 (its initialisation) and 4 (a sharper, trained-like value).
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform

import torch
import torch.nn.functional as F

from d2turb.models.injection import ASPI, CosineASPI
from d2turb.models.rectifier import ConvGELU

SIZES = [(256, 256), (1024, 1024), (1080, 1920)]


def content(size: tuple[int, int]) -> torch.Tensor:
    from skimage import data

    img = torch.from_numpy(data.astronaut()).float().div(255).permute(2, 0, 1)[None]
    return F.interpolate(img, size=size, mode="bicubic", align_corners=False, antialias=True).clamp(0, 1)


def stats(attn: torch.Tensor) -> dict:
    p = attn.double().clamp_min(1e-300)
    entropy = -(p * p.log()).sum(-1).mean().item()
    return {
        "entropy": entropy,
        "entropy_rel": entropy / math.log(attn.shape[-1]),
        "row_max": attn.amax(-1).mean().item(),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", help="also write the JSON here")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()

    torch.manual_seed(args.seed)
    project = ConvGELU(3, 32)  # the authors' input projection: F_shallow
    embed_guide = torch.nn.Conv2d(3, 96, 1)  # stand-in for F_guide
    variants = {"aspi (authors)": ASPI(32, 96)}
    for tau in (1.0, 4.0):
        cos = CosineASPI(32, 96, heads=4)
        with torch.no_grad():
            cos.temperature.fill_(tau)
        variants[f"aspi_cosine (tau={tau:g})"] = cos

    results: dict = {name: {} for name in variants}
    ref: dict = {}
    with torch.no_grad():
        for h, w in SIZES:
            img = content((h, w))
            shallow, guide = project(img), torch.tanh(embed_guide(img))
            for name, module in variants.items():
                delta, attn = module.attend(shallow, guide, return_attn=True)
                row = stats(attn)
                if (h, w) == SIZES[0]:
                    ref[name] = (delta, attn)
                else:
                    d0, a0 = ref[name]
                    down = F.interpolate(delta, size=SIZES[0], mode="area")
                    row["attn_change"] = (attn - a0).abs().mean().item()
                    row["output_change"] = ((down - d0).norm() / d0.norm()).item()
                results[name][f"{w}x{h}"] = row
    report = {
        "benchmark": "aspi_resolution",
        "sizes": [f"{w}x{h}" for h, w in SIZES],
        "results": results,
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "torch": torch.__version__,
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": "python3 benchmarks/bench_aspi_resolution.py",
    }
    text = json.dumps(report, indent=2)
    print(text)
    if args.out:
        from d2turb.io import write_text

        write_text(args.out, text + "\n")


if __name__ == "__main__":
    main()
