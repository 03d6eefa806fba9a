"""`d2turb make-dataset` (placeholder until implemented)."""
from d2turb.errors import D2TurbError


def register(sub):
    p = sub.add_parser("make-dataset", help="(not implemented yet)")
    p.set_defaults(func=run)


def run(args):
    raise D2TurbError("'make-dataset' is not implemented yet")
