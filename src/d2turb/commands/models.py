"""`d2turb models` (placeholder until implemented)."""
from d2turb.errors import D2TurbError


def register(sub):
    p = sub.add_parser("models", help="(not implemented yet)")
    p.set_defaults(func=run)


def run(args):
    raise D2TurbError("'models' is not implemented yet")
