"""End-to-end speed and peak memory of ``d2turb restore CLIP --temporal N`` on the real 1080p clip (issue 35:
≥ 2 frames/s and ≤ 2 GB peak on the idle 2-core machine, default options, ``--temporal 16``).

    python3 benchmarks/bench_clip_1080p.py [--clip ../shared/data/real/dost_street_clip] [--temporal 16]
        [--frames N] [--json benchmarks/results/clip_1080p.json] [-- extra restore options]

Runs ``python -m d2turb restore CLIP --temporal N --out TMP`` in a child process (a folder of the first ``--frames``
frames when given, as symlinks), wall time from start to exit (interpreter start-up, imports, decoding, registration,
fusion, the blind deblur, writing the PNGs and the mp4) and the child's peak resident memory
(``resource.getrusage(RUSAGE_CHILDREN).ru_maxrss``) and CPU time (user + system: what the run costs whatever the
load of a shared machine; wall time on an idle machine is at least cpu_s / cores). Skips (exit 0, a note) when
the clip is absent. Prints one JSON object (and writes it to ``--json``).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
DEFAULT_CLIP = HERE.parent.parent / "shared" / "data" / "real" / "dost_street_clip"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clip", default=str(DEFAULT_CLIP))
    ap.add_argument("--temporal", type=int, default=16)
    ap.add_argument("--frames", type=int, default=None, help="only the first N frames (default: all)")
    ap.add_argument("--json", help="also write the JSON here")
    ap.add_argument("extra", nargs="*", help="more `d2turb restore` options (after --)")
    args = ap.parse_args()
    clip = Path(args.clip)
    if not clip.is_dir():
        print(f"note: {clip} is absent (shared data): nothing to time", file=sys.stderr)
        return
    with tempfile.TemporaryDirectory() as tmp:
        src = clip
        files = sorted(p for p in clip.iterdir() if p.suffix.lower() in (".jpg", ".png"))
        if args.frames:
            src = Path(tmp) / "frames"
            src.mkdir()
            for f in files[: args.frames]:
                (src / f.name).symlink_to(f.resolve())
            files = files[: args.frames]
        cmd = [sys.executable, "-m", "d2turb", "restore", str(src), "--temporal", str(args.temporal)]
        cmd += ["--out", str(Path(tmp) / "out"), *args.extra]
        t0 = time.perf_counter()
        r = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "TQDM_DISABLE": "1"})
        wall = time.perf_counter() - t0
        if r.returncode != 0:
            sys.exit(f"restore failed ({r.returncode}): {r.stderr[-2000:]}")
        record = json.loads((Path(tmp) / "out" / "restore.json").read_text())
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    peak_kb, cpu_s = usage.ru_maxrss, usage.ru_utime + usage.ru_stime
    out = {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "machine": f"{platform.node()} {platform.machine()}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}",
        "command": " ".join(["d2turb", *cmd[3:4], clip.name, *cmd[5:7], *args.extra]),
        "frames": len(files),
        "wall_s": round(wall, 2),
        "frames_per_s": round(len(files) / wall, 3),
        "peak_rss_gb": round(peak_kb / 1e6, 3),
        "cpu_s": round(cpu_s, 1),  # user + system: on a loaded machine, the idle wall time is at least cpu_s / cores
        "frames_per_cpu_s": round(len(files) / cpu_s, 3),
        "deblur": record.get("deblur"),
        "notes": [line for line in r.stderr.splitlines() if line.startswith("note:")],
    }
    text = json.dumps(out, indent=1)
    print(text)
    if args.json:
        Path(args.json).write_text(text + "\n")


if __name__ == "__main__":
    main()
