"""Score blind deblurs of cached fused frames (cache.py) against the oracle, the physics deblur at each clip's true
D/r0, optics and depth modulation: PSNR with the global offset removed, per D/r0 bin the gain over ``--deblur none``,
its share of the oracle's gain, the worst clip, the gain over the input frames.

    python benchmarks/blur_net/evaluate.py --data CACHE_DIRS... --weights blur-net.safetensors --shrink 0 0.5 1 \\
        [--rounds] [--out scores.json]
"""

import argparse
import glob
import json

import numpy as np
import torch

from d2turb.clip.blind import BlindDeblur
from d2turb.clip.deblur import PhysicsDeblur, default_balance
from d2turb.eval.clips import remove_global_offset
from d2turb.eval.metrics import psnr

BINS = ("weak", "medium", "strong")


def score(x, gt) -> float:
    moved, ref, _ = remove_global_offset(torch.as_tensor(x).float().clamp(0, 1), gt)
    return float(psnr(moved[None], ref[None]))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", nargs="+", required=True)
    ap.add_argument("--weights", default=None)
    ap.add_argument("--shrink", type=float, nargs="+", default=[0.5])
    ap.add_argument("--rounds", action="store_true", help="also the edge-based shapes of rounds 1 and 2")
    ap.add_argument("--out")
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = []
    for d in args.data:
        for f in sorted(glob.glob(f"{d}/*.npz")):
            z = np.load(f)
            gt = torch.from_numpy(z["gt"].astype(np.float32))
            fused = [torch.from_numpy(x.astype(np.float32)) for x in z["fused"]]
            dr0, lod, m = float(z["dr0"]), float(z["lod"]), float(z["m"])
            r = {"clip": f, "bin": str(z["bin"]), "dr0": dr0, "lambda_over_d_px": lod, "modulation": m}
            r["input"] = float(np.mean([score(x.astype(np.float32), gt) for x in z["inp"]]))
            r["none"] = float(np.mean([score(x, gt) for x in fused]))
            oracle = PhysicsDeblur(dr0, lod, balance=default_balance(dr0), modulation=m)
            r["oracle"] = float(np.mean([score(oracle(x), gt) for x in fused]))
            shapes = {f"learned{k:g}": BlindDeblur("learned", args.weights, shrink=k) for k in args.shrink}
            if args.rounds:
                shapes.update(physics=BlindDeblur("physics"), gaussian=BlindDeblur("gaussian"))
            for name, deblur in shapes.items():
                deblur.bwd_flow_px = torch.from_numpy(z["flow"][0].astype(np.float32))
                r[name] = float(np.mean([score(deblur(x), gt) for x in fused]))
                r[name + "_record"] = deblur.record
            rows.append(r)
            print(f[-20:], r["bin"], f"D/r0 {dr0:.2f} λ/(D·ifov) {lod:.2f} M {m:.2f}",
                  " ".join(f"{k} {r[k] - r['none']:+.2f}" for k in ["oracle", *shapes]), flush=True)  # fmt: skip
    names = ["oracle", *[k for k in rows[0] if k.startswith(("learned", "physics", "gaussian")) and "_" not in k]]
    summary = {}
    for b in BINS:
        rb = [r for r in rows if r["bin"] == b]
        if not rb:
            continue
        og = float(np.mean([r["oracle"] - r["none"] for r in rb]))
        s = {"clips": len(rb), "none_over_input": float(np.mean([r["none"] - r["input"] for r in rb]))}
        for k in names:
            g = np.array([r[k] - r["none"] for r in rb])
            s[k] = {"gain": float(g.mean()), "share_of_oracle": float(g.mean() / og), "worst": float(g.min()),
                    "over_input": float(np.mean([r[k] - r["input"] for r in rb]))}  # fmt: skip
        summary[b] = s
    for k in names:
        summary[k + " clips below none by > 0.3 dB"] = int(sum(r[k] - r["none"] < -0.3 for r in rows))
    print(json.dumps(summary, indent=1))
    if args.out:
        with open(args.out, "w") as fh:
            json.dump({"summary": summary, "clips": rows}, fh, indent=1, default=str)


if __name__ == "__main__":
    main()
