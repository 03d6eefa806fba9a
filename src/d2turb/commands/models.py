"""`d2turb models`: list the registered models and backbones with their parameter counts."""

from __future__ import annotations


def register(sub):
    p = sub.add_parser(
        "models",
        help="list models and backbones with parameter counts and where their weights come from",
        description="List registered models (complete D²Turb variants and plain backbones used as "
        "standalone restorers) and backbones, with parameter counts of their default configs, and the weights "
        "shipped in the package (the recommended one, marked *, is the default of restore and demo); for a model "
        "without shipped weights, how to get them: train it (a config in configs/) or convert the authors' checkpoint.",
    )
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(func=run)


# How to get weights for each model that has none in the package: a training config of the repository's configs/
# (tests/test_models_cli.py checks that each names its model), and for the paper model also the authors' checkpoint
# through `convert`.
TRAIN_CONFIGS = {
    "adair": "adair.yaml",
    "atnet": "atnet.yaml",
    "d2turb": "d2turb_restormer_aspi.yaml",
    "d2turb_adair": "d2turb_adair_aspi.yaml",
    "d2turb_focalnet": "d2turb_focalnet_aspi.yaml",
    "d2turb_lite": "d2turb_lite.yaml",
    "d2turb_small": "d2turb_small.yaml",
    "focalnet": "focalnet.yaml",
    "nafnet": "nafnet.yaml",
    "restormer": "restormer.yaml",
    "tmt": "tmt.yaml",
    "turbnet": "turbnet.yaml",
}
CONVERTIBLE = {"d2turb": "d2turb convert CKPT.pth d2turb.safetensors (the authors' checkpoint, HertzDot222/D2Turb)"}


def weights_column(name: str, shipped: list[dict]) -> dict:
    """Where a model's weights come from: ``shipped`` (names of the package's weights files for it, recommended
    first), else ``convert`` (the authors' checkpoint) and/or ``train`` (a config in configs/)."""
    mine = sorted((w for w in shipped if w["model"] == name), key=lambda w: not w["recommended"])
    entry = {"shipped": [w["name"] for w in mine]}
    if name in CONVERTIBLE:
        entry["convert"] = CONVERTIBLE[name]
    if name in TRAIN_CONFIGS:
        entry["train"] = f"d2turb train --config configs/{TRAIN_CONFIGS[name]}"
    return entry


def describe_weights(entry: dict, recommended: str) -> str:
    """The table's weights column: shipped names, else the ways to get weights."""
    if entry["shipped"]:
        return "shipped: " + ", ".join(n + ("*" if n == recommended else "") for n in entry["shipped"])
    ways = (["convert the authors' checkpoint"] if "convert" in entry else []) + (
        ["train: " + entry["train"].rsplit(" ", 1)[-1]] if "train" in entry else []
    )
    return ", or ".join(ways) if ways else "none"


def run(args):
    # lazy: see d2turb.commands
    import json

    import torch

    from d2turb.models import create_backbone, list_backbones, list_models, parameter_count
    from d2turb.models.hub import RECOMMENDED_WEIGHTS, shipped_weights, shipped_weights_dir
    from d2turb.models.weights import weights_info

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
    for m in models:
        m["weights"] = weights_column(m["name"], shipped)
    if args.json:
        print(json.dumps({"models": models, "backbones": backbones, "shipped_weights": shipped}, indent=2))
        return 0
    print("models (default config):")
    print(f"  {'name':<15} {'params':>8}  weights")
    for m in models:
        weights = describe_weights(m["weights"], RECOMMENDED_WEIGHTS)
        print(f"  {m['name']:<15} {m['params'] / 1e6:6.2f} M  {weights}")
    print("  weights: shipped = in the package (* = the default of restore and demo);")
    print("    train = d2turb train --config configs/FILE in a checkout (docs/training.md; the large ones want a GPU);")
    print("    convert = d2turb convert CKPT.pth d2turb.safetensors, the authors' checkpoint (docs/models.md)")
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
