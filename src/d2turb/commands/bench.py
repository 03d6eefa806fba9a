"""`d2turb bench model`: parameters, FLOPs/MACs and latency of a model, or the efficiency table of the registry."""

from __future__ import annotations

from d2turb.commands.common import model_config
from d2turb.defaults import DEFAULT_DEVICE
from d2turb.errors import D2TurbError


def register(sub):
    p = sub.add_parser("bench", help="benchmark models (params, FLOPs/MACs, latency)")
    what = p.add_subparsers(dest="bench_target", metavar="TARGET")
    m = what.add_parser(
        "model",
        help="params, FLOPs/MACs at --size and forward latency of a model",
        description="FLOPs are counted with torch FlopCounterMode (convolutions and matmuls, "
        "MACs = FLOPs/2); 'conv GMACs' counts convolutions only, the papers' convention. With --all: the paper's "
        "efficiency table (its methods with its parameter counts beside ours), then the project's other models.",
    )
    m.add_argument("name", nargs="?", help="registered model (see `d2turb models`)")
    m.add_argument("--all", action="store_true", help="efficiency table of the whole registry")
    m.add_argument("--backbone", help="backbone of a d2turb model")
    m.add_argument("--injection", choices=["aspi", "concat", "none"], help="injection of a d2turb model")
    m.add_argument("--config", help="extra model config as JSON (string or path to a .json file)")
    m.add_argument("--size", type=int, default=256, help="square input size (default 256)")
    m.add_argument(
        "--device",
        default=DEFAULT_DEVICE,
        help=f"latency device: cpu, cuda, or auto (cpu, plus cuda when a GPU is present; default {DEFAULT_DEVICE})",
    )
    m.add_argument("--warmup", type=int, default=1, help="untimed forwards first (default 1)")
    m.add_argument("--repeats", type=int, default=3, help="timed forwards, the median is reported (default 3)")
    m.add_argument("--no-latency", action="store_true", help="only params and FLOPs (no forward pass is run)")
    m.add_argument("--out", help="write the result to FILE.md (Markdown table) or FILE.json")
    p.set_defaults(func=run)


def _config(args) -> dict:
    cfg = model_config(args.config)
    for key in ("backbone", "injection"):
        if getattr(args, key):
            cfg[key] = getattr(args, key)
    return cfg


def run(args):
    # lazy: see d2turb.commands
    import torch

    from d2turb.device import resolve_device
    from d2turb.io import write_json, write_text
    from d2turb.models.complexity import benchmark, efficiency_entries, latency_devices, markdown_table

    if args.bench_target != "model":
        raise D2TurbError("usage: d2turb bench model NAME [options] (or --all)")
    if bool(args.name) == bool(args.all):
        raise D2TurbError("bench model: give exactly one of a model NAME or --all")
    if args.size < 8 or args.repeats < 1 or args.warmup < 0:
        raise D2TurbError("bench model: need --size >= 8, --repeats >= 1, --warmup >= 0")
    if args.out and not args.out.endswith((".md", ".json")):
        raise D2TurbError(f"--out {args.out}: must end in .md or .json")
    devices = [str(resolve_device(d)) for d in latency_devices(args.device)]
    entries = efficiency_entries() if args.all else [(args.name, _config(args))]
    results = []
    for name, cfg in entries:
        results.append(benchmark(name, cfg, args.size, devices, args.warmup, args.repeats, latency=not args.no_latency))
    table = markdown_table(results)
    print(table, end="")
    if args.out:
        if args.out.endswith(".json"):
            write_json(args.out, results if args.all else results[0])
        else:
            write_text(
                args.out,
                f"Parameters and FLOPs of one inference forward at {args.size}² (torch FlopCounterMode on the meta "
                f"device: convolutions and matmuls, MACs = FLOPs/2; conv GMACs = convolutions only, the papers' "
                f'"GFLOPs"); latency = median of {args.repeats} forwards after {args.warmup} warm-up (batch 1, '
                f"fp32, {torch.get_num_threads()} CPU threads); paper = the D²Turb paper's efficiency table."
                f"\n\n{table}",
            )
    return 0
