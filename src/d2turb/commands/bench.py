"""`d2turb bench` (placeholder until implemented)."""
from d2turb.errors import D2TurbError


def register(sub):
    p = sub.add_parser("bench", help="(not implemented yet)")
    p.set_defaults(func=run)


def run(args):
    raise D2TurbError("'bench' is not implemented yet")
