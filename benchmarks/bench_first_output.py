"""Time to first output and total time of `d2turb make-dataset`, `d2turb simulate-video` (issue 26, item 6) and
`d2turb restore CLIP --temporal 16` (issue 52, acceptance 3).

    python3 benchmarks/bench_first_output.py --image PHOTO --clean DIR --src before=OLD/src --src after=NEW/src
        [--env before:OMP_WAIT_POLICY=PASSIVE] [--reps 3] [--commands make-dataset simulate-video] [--nice 5]
    python3 benchmarks/bench_first_output.py --commands restore --clip CLIP --src before=OLD/src --src after=NEW/src
        [--restore-args="--deblur none"] [--reps 5] [--nice 0]

Each run is a fresh `python3 -m d2turb ...` process with PYTHONPATH set to one --src tree (OMP_WAIT_POLICY removed
from the inherited environment, so only --env sets it); the sources alternate within each repetition, so both
see the same machine load. The first output is the first finished sample file (make-dataset: DATASET/turb/NNNNNNN.png;
simulate-video: OUT/turb/000000.png; restore: the first OUT/*_restored.png), found by polling every 10 ms, timed from
the process start (imports included); the total includes restore's mp4.
CPU time is the child's user + system time. Prints one JSON line per run, then the medians per source.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

NEEDS = {"make-dataset": "clean", "simulate-video": "image", "restore": "clip"}  # command -> the input it needs


def command_line(name: str, args, out: Path) -> list[str]:
    if name == "make-dataset":
        return [
            "make-dataset", "--clean", args.clean, "--out", str(out), "--pairs", str(args.pairs), "--patch", "256",
            "--batch", str(args.batch), "--device", "cpu", "--no-progress",
        ]  # fmt: skip
    if name == "restore":
        return ["restore", args.clip, "--temporal", str(args.temporal), "--out", str(out), *args.restore_args.split()]
    return ["simulate-video", args.image, "--out", str(out), "--frames", str(args.frames), "--device", "cpu"]


def first_output(name: str, out: Path) -> bool:
    if name == "restore":  # written atomically (write_image), so a name that exists is a whole frame
        try:
            return any(p.name.endswith("_restored.png") for p in out.iterdir())
        except OSError:
            return False
    folder = out / "turb"
    if name == "simulate-video":
        return (folder / "000000.png").is_file()
    try:
        return any(re.fullmatch(r"\d{7}\.png", p.name) for p in folder.iterdir())
    except OSError:
        return False


def run_once(name: str, label: str, src: str, extra_env: dict, args, work: Path) -> dict:
    out = work / f"{name}-{label}"
    shutil.rmtree(out, ignore_errors=True)
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    env.update(extra_env, PYTHONPATH=src)
    cmd = ["nice", "-n", str(args.nice), sys.executable, "-m", "d2turb", *command_line(name, args, out)]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    load = os.getloadavg()[0]
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    first = None
    while proc.poll() is None:
        if first is None and first_output(name, out):
            first = time.perf_counter() - start
        time.sleep(0.01)
    total = time.perf_counter() - start
    err = proc.stderr.read()
    if proc.returncode != 0:
        raise SystemExit(f"{label} {name} failed ({proc.returncode}): {err[-2000:]}")
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if first is None:  # finished between two polls
        first = total
    return dict(command=name, src=label, first_output_s=round(first, 2), total_s=round(total, 2), cpu_s=round(cpu, 2),
                load_1min=round(load, 2), env=extra_env)  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--src", action="append", required=True, metavar="LABEL=PATH", help="a source tree to run")
    ap.add_argument("--env", action="append", default=[], metavar="LABEL:KEY=VALUE", help="extra env for one label")
    ap.add_argument("--image", help="the photo for simulate-video")
    ap.add_argument("--clean", help="clean-image folder for make-dataset")
    ap.add_argument("--clip", help="the clip (video or folder of frames) for restore")
    ap.add_argument("--temporal", type=int, default=16, help="restore's --temporal")
    ap.add_argument("--restore-args", default="", help="more options of restore, one string")
    ap.add_argument("--pairs", type=int, default=8)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--nice", type=int, default=5)
    ap.add_argument("--commands", nargs="+", default=["make-dataset", "simulate-video"], choices=list(NEEDS))
    args = ap.parse_args()
    for name in args.commands:
        if getattr(args, NEEDS[name]) is None:
            ap.error(f"{name} needs --{NEEDS[name]}")
    srcs = dict(s.split("=", 1) for s in args.src)
    envs: dict[str, dict] = {label: {} for label in srcs}
    for item in args.env:
        label, kv = item.split(":", 1)
        key, value = kv.split("=", 1)
        envs[label][key] = value
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.reps):
            for name in args.commands:
                order = list(srcs) if rep % 2 == 0 else list(srcs)[::-1]
                for label in order:
                    row = run_once(name, label, srcs[label], envs[label], args, Path(tmp))
                    rows.append(row)
                    print(json.dumps(row), flush=True)
    for name in args.commands:
        for label in srcs:
            mine = [r for r in rows if r["command"] == name and r["src"] == label]
            med = {k: round(statistics.median(r[k] for r in mine), 2) for k in ("first_output_s", "total_s", "cpu_s")}
            print(json.dumps(dict(command=name, src=label, runs=len(mine), median=med)))


if __name__ == "__main__":
    main()
