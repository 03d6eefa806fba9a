"""`d2turb convert`: a checkpoint (the authors' .pth, a plain state dict, or a d2turb file) → d2turb .safetensors."""

from __future__ import annotations

from d2turb.commands.common import model_config
from d2turb.errors import D2TurbError


def register(sub):
    p = sub.add_parser(
        "convert",
        help="convert a checkpoint (e.g. the authors' .pth) to d2turb .safetensors weights",
        description="Reads SRC (.pth/.pt/.ckpt/.bin with torch.load(weights_only=True), or .safetensors): a "
        "state dict, possibly nested under params_ema / params / state_dict / model and with module. prefixes, in "
        "the authors' key layout (HertzDot222/D2Turb) or ours. Loads it strictly into the model (any missing, "
        "unexpected or mis-shaped key, or NaN/Inf weight, is an error) and writes DST with the model config and a "
        "checksum.",
    )
    p.add_argument("src", metavar="SRC", help="checkpoint to read")
    p.add_argument("dst", metavar="DST", help="output .safetensors file")
    p.add_argument("--model", default="d2turb", help="registered model the weights belong to (default d2turb)")
    p.add_argument("--config", help="model config as JSON (string or path to a .json file); default: the paper's")
    p.add_argument(
        "--key",
        help="take the state dict from this entry of SRC (default: the first of params_ema, "
        "params, state_dict, model present)",
    )
    p.set_defaults(func=run)


def run(args):
    # lazy: see d2turb.commands
    from pathlib import Path

    from d2turb.models import count_parameters, load_pretrained, save_pretrained

    dst = Path(args.dst)
    if dst.suffix != ".safetensors":
        raise D2TurbError(f"{dst}: output must end in .safetensors")
    if Path(args.src).resolve() == dst.resolve():
        raise D2TurbError(f"{dst}: output must differ from the input")
    model = load_pretrained(args.src, model=args.model, config=model_config(args.config), key=args.key)
    save_pretrained(model, dst)
    print(f"{dst}: {model.config['name']}, {count_parameters(model):,} parameters")
    return 0
