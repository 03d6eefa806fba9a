"""Benchmark D²Turb models: params, FLOPs/MACs (FlopCounterMode) and forward latency, printed as JSON.

python benchmarks/bench_model.py --all --size 256 --device cpu
python benchmarks/bench_model.py d2turb --config '{"backbone": "nafnet"}' --device cuda
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform

import torch

from d2turb.commands.common import model_config
from d2turb.models.complexity import benchmark, efficiency_entries


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("name", nargs="?", default="d2turb")
    p.add_argument("--config", help="model config as JSON (string or path to a .json file)")
    p.add_argument("--all", action="store_true", help="every row of the efficiency table")
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--warmup", type=int, default=1)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--dtype", choices=["float32", "bfloat16"], default="float32")
    args = p.parse_args()
    entries = efficiency_entries() if args.all else [(args.name, model_config(args.config))]
    if args.device.startswith("cuda"):
        machine = torch.cuda.get_device_name()
    else:
        machine = (
            f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, {torch.get_num_threads()} threads"
        )
    for name, cfg in entries:
        load_before = os.getloadavg()[0]
        r = benchmark(name, cfg, args.size, args.device, args.warmup, args.repeats, dtype=getattr(torch, args.dtype))
        # the load average shows how contended the CPU was (a shared 2-core machine inflates latency)
        r.update(
            load_avg=[load_before, os.getloadavg()[0]],
            machine=machine,
            torch=torch.__version__,
            date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        )
        print(json.dumps(r), flush=True)


if __name__ == "__main__":
    main()
