"""`d2turb check-dataset`: verify a generated dataset; exit 1 with the list of problems if broken."""

from __future__ import annotations

import sys


def register(sub):
    p = sub.add_parser(
        "check-dataset",
        help="verify a dataset made by make-dataset",
        description="Checks files, decoding, shapes, NaN in flow, orphans, duplicates and bins.",
    )
    p.add_argument("root", metavar="DIR", help="dataset folder")
    p.add_argument("--quick", action="store_true", help="check file presence only, do not decode")
    p.add_argument("--max-problems", type=int, default=50, help="problems listed at most (default 50)")
    p.set_defaults(func=run)


def run(args):
    # lazy: see d2turb.commands
    from d2turb.data.check import check_dataset

    report = check_dataset(args.root, decode=not args.quick)
    counts = ", ".join(f"{name} {n}" for name, n in report.counts.items())
    print(f"{args.root}: {report.samples} samples ({counts})")
    if report.ok:
        print("ok")
        return 0
    print(f"{len(report.problems)} problem(s):", file=sys.stderr)
    for problem in report.problems[: args.max_problems]:
        print(f"  {problem}", file=sys.stderr)
    if len(report.problems) > args.max_problems:
        print(f"  ... and {len(report.problems) - args.max_problems} more", file=sys.stderr)
    return 1
