"""Latency of `d2turb restore - --temporal N --out DIR` on a y4m stream written to its standard input at a steady
frame rate (issue 52 item 2): for each frame t, the time from its capture (the feed's start + t/fps, when a camera
would have it) until the t-th ``*_restored.png`` exists in DIR (written atomically; polled every 5 ms). A frame the
command does not read yet waits in the pipe (``feed_lag_max_s``: the most a frame was written late).

    python3 benchmarks/bench_stream_latency.py FRAMES_DIR --fps 10 [--src PATH/src] [--temporal 16] [--pingpong 2]
        [-- MORE OPTIONS]

FRAMES_DIR holds the clip's frames (PNG, one size), played forward and back ``--pingpong`` times. Prints one JSON
line: the median and largest latency of the steady outputs (from the window's end on, up to the last that still
waits for an input frame), and the windows' lookahead ``--ahead`` (output t needs input t + ahead: T/2 − 1 for a
stream since 2092e34, ``restore --lookahead``; 3·(T/2 − 1) with 2 registration rounds over centred windows before).
The feed starts with the command, so the first outputs also wait for its start-up.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from PIL import Image


def y4m_frame(rgb: np.ndarray) -> bytes:
    """An (H,W,3) uint8 frame as a y4m C444 frame (BT.601 luma and colour differences, full range)."""
    r, g, b = (rgb[..., i].astype(np.float32) for i in range(3))
    y = 0.299 * r + 0.587 * g + 0.114 * b
    planes = (y, (b - y) * 0.564 + 128, (r - y) * 0.713 + 128)
    return b"FRAME\n" + b"".join(np.clip(np.rint(p), 0, 255).astype(np.uint8).tobytes() for p in planes)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("frames", type=Path)
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--temporal", type=int, default=16)
    ap.add_argument("--src", help="PYTHONPATH of the d2turb to run (default: the installed one)")
    ap.add_argument("--pingpong", type=int, default=2, help="the frames played forward and back this many times")
    ap.add_argument("--ahead", type=int, default=None, help="the run's lookahead in frames (default T/2 - 1)")
    ap.add_argument("more", nargs="*", help="more options of restore (after --)")
    a = ap.parse_args()
    clip = [np.asarray(Image.open(f).convert("RGB")) for f in sorted(a.frames.glob("*.png"))]
    frames = [f for k in range(a.pingpong) for f in (clip if k % 2 == 0 else clip[::-1])]
    h, w = frames[0].shape[:2]
    env = dict(os.environ, **({"PYTHONPATH": a.src} if a.src else {}))
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        cmd = [sys.executable, "-m", "d2turb", "restore", "-", "--temporal", str(a.temporal), "--out", str(out)]
        cmd += a.more
        start = time.perf_counter()
        proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
        captured: list[float] = []  # when a camera would have had each frame
        lag = [0.0]

        def feed():
            proc.stdin.write(f"YUV4MPEG2 W{w} H{h} F{round(a.fps)}:1 Ip A1:1 C444\n".encode())
            t0 = time.perf_counter()
            for i, f in enumerate(frames):
                captured.append(t0 + i / a.fps)
                time.sleep(max(0.0, captured[-1] - time.perf_counter()))
                proc.stdin.write(y4m_frame(f))
                proc.stdin.flush()
                lag[0] = max(lag[0], time.perf_counter() - captured[-1])
            proc.stdin.close()

        feeder = threading.Thread(target=feed)
        feeder.start()
        seen: dict[str, float] = {}
        while proc.poll() is None:
            now = time.perf_counter()
            if out.is_dir():
                for p in out.iterdir():
                    if p.name.endswith("_restored.png"):
                        seen.setdefault(p.name, now)
            time.sleep(0.005)
        feeder.join()
        err = proc.stderr.read().decode()
        shutil.rmtree(out, ignore_errors=True)
    if proc.returncode:
        raise SystemExit(f"restore failed ({proc.returncode}): {err[-2000:]}")
    done = [seen[n] for n in sorted(seen)]
    latency = [t - s for t, s in zip(done, captured)]
    ahead = a.temporal // 2 - 1 if a.ahead is None else a.ahead
    steady = latency[a.temporal : len(latency) - ahead] or latency
    print(json.dumps({
        "fps": a.fps, "temporal": a.temporal, "frames": len(done), "first_output_s": round(done[0] - start, 2),
        "latency_median_s": round(statistics.median(steady), 3), "latency_max_s": round(max(steady), 3),
        "steady_outputs": len(steady), "lookahead_s": round(ahead / a.fps, 3), "feed_lag_max_s": round(lag[0], 3),
        "load_1min": round(os.getloadavg()[0], 2), "options": a.more,
    }))  # fmt: skip


if __name__ == "__main__":
    main()
