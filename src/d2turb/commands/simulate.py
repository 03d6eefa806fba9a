"""`d2turb simulate` (placeholder until implemented)."""
from d2turb.errors import D2TurbError


def register(sub):
    p = sub.add_parser("simulate", help="(not implemented yet)")
    p.set_defaults(func=run)


def run(args):
    raise D2TurbError("'simulate' is not implemented yet")
