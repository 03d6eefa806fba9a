"""Does NIQE order clip restorations as the truth does? Simulated clips, where the clean image is known (issue 23).

    PYTHONPATH=src python3 benchmarks/clip_niqe_truth.py --clips DATASET_DIR [--temporal 32] [--first 8]
        [--stride 8] [--json FILE]

DATASET_DIR is a sequence dataset (``d2turb make-dataset --frames N``). For each clip, ``ClipRestorer(temporal)``
with the physics deblur at the clip's true D/r0 and optics (as ``d2turb evaluate --clips`` does), and for every
``--stride``-th frame from ``--first``: NIQE, PIQE and PSNR against the clean image of the input frame, the fused
frame, the restored frame, the same Wiener filter on the single input frame (the comparison of issue 23's acceptance
2) and the clean image itself. Per clip and score, whether the restored frames' mean is below both the input's and
the single-frame filter's (the acceptance's test), and whether the clean image's is below the input's. Means per
bin; prints and writes one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
from pathlib import Path

import numpy as np
import torch

from d2turb.clip import ClipRestorer
from d2turb.data.sequence import SequenceDataset
from d2turb.eval.clips import physics_deblur_for
from d2turb.eval.metrics import psnr, quantise_8bit
from d2turb.eval.niqe import niqe
from d2turb.eval.piqe import piqe

ROWS = ("input", "fused", "restored", "single-frame filter", "clean")
BINS = ("weak", "medium", "strong")


def _restored_passes(mean: dict[str, float]) -> bool:
    """Issue 23's acceptance 2 on one clip: the restored frames score below the input and the single-frame filter."""
    return mean["restored"] < min(mean["input"], mean["single-frame filter"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--clips", type=Path, required=True)
    ap.add_argument("--temporal", type=int, default=32)
    ap.add_argument("--first", type=int, default=8)
    ap.add_argument("--stride", type=int, default=8)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    data = SequenceDataset(args.clips)
    clips, per_bin = [], {(b, r): [] for b in BINS for r in ROWS}
    for i in range(len(data)):
        item, record = data[i], data.records[i]
        deblur = physics_deblur_for(record, item["depth"])
        frames = list(item["turb"])
        wanted = set(range(args.first, len(frames) - args.first + 1, args.stride))
        clean = quantise_8bit(item["gt"])
        scores = {r: [] for r in ROWS}
        scores["clean"].append((float(niqe(clean)), float(piqe(clean)), None))  # one clean image per clip
        for out in ClipRestorer(temporal=args.temporal, deblur=deblur).restore(frames):
            if out.index not in wanted:
                continue
            images = {
                "input": frames[out.index],
                "fused": out.fused,
                "restored": out.restored,
                "single-frame filter": deblur(frames[out.index]),
            }
            for r, x in images.items():
                x = quantise_8bit(x)
                scores[r].append((float(niqe(x)), float(piqe(x)), float(psnr(x, item["gt"]))))
        niqe_mean = {r: float(np.mean([s[0] for s in v])) for r, v in scores.items()}
        piqe_mean = {r: float(np.mean([s[1] for s in v])) for r, v in scores.items()}
        for r, v in scores.items():
            per_bin[(record["bin"], r)].extend(v)
        clips.append(
            {
                "id": record["id"],
                "bin": record["bin"],
                "dr0": round(float(record["dr0"]), 3),
                "niqe": {r: round(v, 3) for r, v in niqe_mean.items()},
                "piqe": {r: round(v, 2) for r, v in piqe_mean.items()},
                "restored_passes": _restored_passes(niqe_mean),
                "clean_below_input": niqe_mean["clean"] < niqe_mean["input"],
                "piqe_restored_passes": _restored_passes(piqe_mean),
                "piqe_clean_below_input": piqe_mean["clean"] < piqe_mean["input"],
            }
        )
        print(json.dumps(clips[-1]), flush=True)
    table = {
        b: {
            r: {
                "niqe": round(float(np.mean([s[0] for s in per_bin[(b, r)]])), 3),
                "piqe": round(float(np.mean([s[1] for s in per_bin[(b, r)]])), 2),
                "psnr": None if r == "clean" else round(float(np.mean([s[2] for s in per_bin[(b, r)]])), 2),
            }
            for r in ROWS
        }
        for b in BINS
        if per_bin[(b, "input")]
    }
    result = {
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "torch": torch.__version__},
        "per_bin": table,
        "clips_restored_pass": sum(c["restored_passes"] for c in clips),
        "clips_clean_below_input": sum(c["clean_below_input"] for c in clips),
        "clips_piqe_restored_pass": sum(c["piqe_restored_passes"] for c in clips),
        "clips_piqe_clean_below_input": sum(c["piqe_clean_below_input"] for c in clips),
        "clips": clips,
    }
    text = json.dumps(result, indent=1)
    if args.json:
        args.json.write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
