"""`d2turb check-dataset` (placeholder until implemented)."""
from d2turb.errors import D2TurbError


def register(sub):
    p = sub.add_parser("check-dataset", help="(not implemented yet)")
    p.set_defaults(func=run)


def run(args):
    raise D2TurbError("'check-dataset' is not implemented yet")
