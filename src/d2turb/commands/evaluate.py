"""`d2turb evaluate` (placeholder until implemented)."""
from d2turb.errors import D2TurbError


def register(sub):
    p = sub.add_parser("evaluate", help="(not implemented yet)")
    p.set_defaults(func=run)


def run(args):
    raise D2TurbError("'evaluate' is not implemented yet")
