"""The blind deblur's shapes against the oracle on simulated clips with known truth (docs/clips.md, "The blind
deblur", round 2): per clip, the fused frames (ClipRestorer, window ``--temporal``, frames ``--frames``) are cached
with the physics deblur at the clip's true D/r0 and optics (the oracle, ``eval.clips.physics_deblur_for``), then
``BlindDeblur("physics")`` (the default) and ``BlindDeblur("gaussian")`` (round 1) are scored by PSNR with the global
offset removed; per bin the share of the oracle's gain over ``--deblur none`` and the worst clip.

    python benchmarks/clip_blind_shapes.py --out blind_shapes.json val_L1 val_L2 ...   # make-dataset clip folders
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from d2turb.clip import ClipRestorer
from d2turb.clip.blind import BlindDeblur
from d2turb.data.sequence import SequenceDataset
from d2turb.eval.clips import physics_deblur_for, remove_global_offset
from d2turb.eval.metrics import psnr

BINS = ("weak", "medium", "strong")


def _psnr(x: torch.Tensor, gt: torch.Tensor) -> float:
    moved, ref, _ = remove_global_offset(x.clamp(0, 1), gt)
    return float(psnr(moved[None], ref[None]))


def cache_clip(root: Path, idx: int, temporal: int, frames: tuple[int, ...]) -> dict:
    path = root / f"blind_cache_{temporal}_{idx}.pt"
    if path.exists():
        return torch.load(path)
    data = SequenceDataset(root)
    item, rec = data[idx], data.records[idx]
    phys = physics_deblur_for(rec, item["depth"])
    kept = {o.index: o.fused for o in ClipRestorer(temporal=temporal).restore(item["turb"]) if o.index in frames}
    fused = torch.stack(list(kept.values()))
    c = {"dr0": float(rec["dr0"]), "bin": rec["bin"], "lod": phys.lambda_over_d_px, "gt": item["gt"], "fused": fused}
    c["phys"] = torch.stack([phys(f) for f in fused])
    c["input"] = item["turb"][list(kept)]
    torch.save(c, path)
    return c


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("roots", nargs="+", type=Path)
    ap.add_argument("--temporal", type=int, default=16)
    ap.add_argument("--frames", type=int, nargs="+", default=[4, 12])
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = []
    for root in args.roots:
        for idx in range(len(SequenceDataset(root))):
            c = cache_clip(root, idx, args.temporal, tuple(args.frames))
            gt = c["gt"]
            r = {"clip": f"{root}/{idx}", "bin": c["bin"], "dr0": c["dr0"], "lambda_over_d_px": c["lod"]}
            for name in ("input", "fused", "phys"):
                r[name] = float(np.mean([_psnr(x, gt) for x in c[name]]))
            for shape in ("physics", "gaussian"):
                d = BlindDeblur(shape)
                r[shape] = float(np.mean([_psnr(d(x), gt) for x in c["fused"]]))
                r[shape + "_record"] = d.record
            rows.append(r)
            gains = [f"{k} {r[k] - r['fused']:+.2f}" for k in ("phys", "physics", "gaussian")]
            print(r["clip"], r["bin"], *gains, flush=True)
    summary = {}
    for shape in ("physics", "gaussian"):
        s = {}
        for b in BINS:
            rb = [r for r in rows if r["bin"] == b]
            if rb:
                gain = np.mean([r[shape] - r["fused"] for r in rb])
                s[b] = {"share_of_oracle": float(gain / np.mean([r["phys"] - r["fused"] for r in rb])), "gain": gain}
        g = np.array([r[shape] - r["fused"] for r in rows])
        s["worst"], s["below_0.3"] = float(g.min()), int((g < -0.3).sum())
        summary[shape] = s
    args.out.write_text(json.dumps({"summary": summary, "clips": rows}, indent=1, default=str))
    print(json.dumps(summary, indent=1, default=float))


if __name__ == "__main__":
    main()
