"""`d2turb models`: list the registered models and backbones with their parameter counts."""

from __future__ import annotations


def register(sub):
    p = sub.add_parser(
        "models",
        help="list models and backbones with parameter counts",
        description="List registered models (complete D²Turb variants and plain backbones used as "
        "standalone restorers) and backbones, with parameter counts of their default configs, and the weights "
        "shipped in the package (the recommended one, marked *, is the default of restore and demo).",
    )
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(func=run)


def run(args):
    # lazy: see d2turb.commands
    import json

    import torch

    from d2turb.models import create_backbone, list_backbones, list_models, parameter_count
    from d2turb.models.hub import RECOMMENDED_WEIGHTS, shipped_weights, shipped_weights_dir, weights_info

    models = [{"name": n, "params": parameter_count(n)} for n in list_models()]
    backbones = []
    for name in list_backbones():
        with torch.device("meta"):
            b = create_backbone(name)
        backbones.append(
            {"name": name, "params": sum(p.numel() for p in b.parameters()), "guide_channels": b.guide_channels}
        )
    shipped = [
        {"name": n, "recommended": n == RECOMMENDED_WEIGHTS, **weights_info(shipped_weights_dir() / f"{n}.safetensors")}
        for n in shipped_weights()
    ]
    if args.json:
        print(json.dumps({"models": models, "backbones": backbones, "shipped_weights": shipped}, indent=2))
        return 0
    print("models (default config):")
    for m in models:
        print(f"  {m['name']:<14} {m['params'] / 1e6:8.2f} M params")
    print("backbones (default config; usable as d2turb backbone=NAME and as a standalone model):")
    for b in backbones:
        print(f"  {b['name']:<14} {b['params'] / 1e6:8.2f} M params, F_guide {b['guide_channels']} channels")
    print("shipped weights (* = recommended: the default of restore and demo; MODEL_CARD.md):")
    for w in shipped:
        mark = "*" if w["recommended"] else " "
        print(f"{mark} {w['name']:<20} model {w['model']}, {w['params'] / 1e6:.2f} M params, {w['bytes'] / 1e6:.1f} MB")
    if not shipped:
        print("  none in this installation")
    return 0
