"""Cache fused frames (ClipRestorer, deblur none) of make-dataset clip folders with their true blur parameters."""

import sys
import time
from pathlib import Path

import numpy as np
import torch

from d2turb.clip import ClipRestorer
from d2turb.data.sequence import SequenceDataset
from d2turb.eval.clips import physics_deblur_for


def main():
    root, out = Path(sys.argv[1]), Path(sys.argv[2])
    frames = tuple(int(x) for x in sys.argv[3].split(",")) if len(sys.argv) > 3 else (4, 20)
    temporal = int(sys.argv[4]) if len(sys.argv) > 4 else 16
    torch.set_num_threads(1)
    out.mkdir(parents=True, exist_ok=True)
    data = SequenceDataset(root)
    t0 = time.time()
    for idx in range(len(data)):
        path = out / f"{idx:05d}.npz"
        if path.exists():
            continue
        item, rec = data[idx], data.records[idx]
        phys = physics_deblur_for(rec, item["depth"])
        fused, flows = [], []
        last = max(frames)
        for o in ClipRestorer(temporal=temporal).restore(item["turb"]):
            if o.index in frames:
                fused.append(o.fused.numpy())
                flows.append(o.bwd_flow_px.numpy())
            if o.index >= last:
                break
        np.savez(
            path.with_suffix(".tmp.npz"),
            fused=np.stack(fused).astype(np.float16),
            flow=np.stack(flows).astype(np.float16),
            gt=item["gt"].numpy().astype(np.float16),
            inp=item["turb"][list(frames)].numpy().astype(np.float16),
            dr0=float(rec["dr0"]),
            lod=float(phys.lambda_over_d_px),
            m=float(phys.modulation),
            bin=str(rec["bin"]),
        )
        path.with_suffix(".tmp.npz").rename(path)
        if idx % 50 == 0:
            print(idx, f"{time.time() - t0:.0f}s", flush=True)


if __name__ == "__main__":
    main()
