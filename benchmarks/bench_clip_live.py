"""The live preset at 1280×720 (issue 52 acceptance 2): where the CPU goes per stage, and frames/s end to end against
the default, in alternating pairs.

    python benchmarks/bench_clip_live.py [--clip CLIP.mp4] [--frames 240] [--temporal 32] [--pairs 2]
                                         [--default-frames 96] [--json FILE]

Without ``--clip`` the clip is made: ``dost_street_clip`` (../shared/data/real, 43 real 1080p frames) resized to
1280×720 and played forth and back to ``--frames`` frames, an mp4 written by the project's writer (x264 veryfast).

1. Stages (in turn, one compute thread each, CPU ms a frame of the whole process, ``time.process_time``: FFmpeg's and
   x264's own threads included): decode (PyAV, as ``restore`` reads a video),
   registration and fusion (:class:`~d2turb.clip.live.LiveRestorer` unthreaded, no deblur), the deblur
   (:func:`~d2turb.clip.live.live_deblurred`: the blind deblur decided on the first frame, then the luma Wiener filter
   and guard), the 8-bit conversion, the mp4 encode (x264 at the live preset's speed preset).
2. End to end: ``d2turb restore CLIP --temporal N --preset fast --out DIR`` (the mp4 only), and the default
   (``--preset balanced``, on the clip's first ``--default-frames``), alternating, each a fresh process: wall time,
   CPU time (user + system of the child), peak RSS, frames/s = frames / wall; the load average before each run.
   The live preset's marginal rate (frames/s once started) from a second run on the first third of the frames.
Prints one JSON object (and writes it to --json FILE).
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real" / "dost_street_clip"


def make_clip(path: Path, frames: int) -> None:
    import cv2

    from d2turb.video import Mp4Writer

    files = sorted(glob.glob(str(REAL / "*")))
    if not files:
        sys.exit(f"no frames in {REAL}: give --clip")
    size = (1280, 720)
    first = [cv2.resize(cv2.cvtColor(cv2.imread(f), cv2.COLOR_BGR2RGB), size, interpolation=cv2.INTER_AREA)
             for f in files]  # fmt: skip
    loop = first + first[-2:0:-1]
    with Mp4Writer(path, 30.0) as out:
        for i in range(frames):
            out.write(loop[i % len(loop)])


def stages(clip: Path, frames: int, temporal: int) -> dict:
    """CPU ms a frame of each stage, one thread each."""
    import torch

    from d2turb.clip.blind import BlindDeblur
    from d2turb.clip.live import LIVE_X264_PRESET, LiveRestorer, live_deblurred
    from d2turb.io.png import to_uint8
    from d2turb.video import VideoSource

    torch.set_num_threads(1)
    import cv2

    cv2.setNumThreads(1)
    t = time.process_time()
    decoded = [f for _, f in zip(range(frames), VideoSource(clip))]
    ms = {"decode": (time.process_time() - t) * 1000 / len(decoded)}
    t = time.process_time()
    fused = [o.fused.permute(1, 2, 0).numpy().copy() for o in LiveRestorer(temporal, threaded=False).restore(decoded)]
    ms["register_fuse"] = (time.process_time() - t) * 1000 / len(fused)
    deblur = BlindDeblur()
    t = time.process_time()
    live_deblurred(deblur, torch.from_numpy(fused[0]).permute(2, 0, 1))
    ms["blind_decision_once"] = (time.process_time() - t) * 1000
    t = time.process_time()
    restored = [live_deblurred(deblur, torch.from_numpy(f).permute(2, 0, 1)) for f in fused[1:]]
    ms["deblur"] = (time.process_time() - t) * 1000 / len(restored)
    t = time.process_time()
    u8 = [to_uint8(r) for r in restored]
    ms["to_uint8"] = (time.process_time() - t) * 1000 / len(u8)
    import av

    with tempfile.TemporaryDirectory() as tmp:
        out = av.open(str(Path(tmp) / "x.mp4"), "w")
        stream = out.add_stream("libx264", rate=30)
        stream.width, stream.height, stream.pix_fmt = 1280, 720, "yuv420p"
        stream.codec_context.thread_type, stream.codec_context.thread_count = "SLICE", 1
        stream.options = {"preset": LIVE_X264_PRESET}
        t = time.process_time()
        for a in u8:
            for p in stream.encode(av.VideoFrame.from_ndarray(a, "rgb24").reformat(format="yuv420p", threads=1)):
                out.mux(p)
        for p in stream.encode():
            out.mux(p)
        ms["encode"] = (time.process_time() - t) * 1000 / len(u8)
        out.close()
    ms["sum_per_frame"] = sum(v for k, v in ms.items() if k != "blind_decision_once")
    return {k: round(v, 2) for k, v in ms.items()}


def run(cmd: list[str]) -> dict:
    """Wall, CPU and peak RSS of a fresh process (GNU time's, which forks a clean child)."""
    load = os.getloadavg()[0]
    with tempfile.NamedTemporaryFile("r", suffix=".time") as timing:
        t = time.perf_counter()
        proc = subprocess.run(["/usr/bin/time", "-o", timing.name, "-f", "%U %S %M"] + cmd, capture_output=True,
                              text=True)  # fmt: skip
        wall = time.perf_counter() - t
        if proc.returncode != 0:
            sys.exit(f"{' '.join(cmd)} failed: {proc.stderr[-2000:]}")
        user, system, kib = timing.read().split()[-3:]
    return {
        "wall_s": round(wall, 2),
        "cpu_s": round(float(user) + float(system), 2),
        "peak_rss_mib": round(int(kib) / 1024, 1),
        "load_before": round(load, 2),
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--clip", default=None)
    ap.add_argument("--frames", type=int, default=240)
    ap.add_argument("--temporal", type=int, default=32)
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--default-frames", type=int, default=96)
    ap.add_argument("--no-stages", action="store_true")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        clip = Path(a.clip) if a.clip else Path(tmp) / "street720.mp4"
        if not a.clip:
            make_clip(clip, a.frames)
        from d2turb.video import video_size

        n, w, h = video_size(clip)
        d2turb = [sys.executable, "-m", "d2turb", "restore", str(clip), "--temporal", str(a.temporal)]
        res = {
            "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
            "cpu_model": next((ln.split(":")[1].strip() for ln in open("/proc/cpuinfo") if "model name" in ln), "?"),
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "clip": {
                "path": str(a.clip or "dost_street_clip at 1280x720, forth and back"),
                "size": [w, h],
                "frames": n,
            },  # fmt: skip
            "settings": vars(a),
            "stages_cpu_ms_per_frame": None if a.no_stages else stages(clip, min(n, 96), a.temporal),
            "pairs": [],
        }
        third = max(a.temporal + 2, n // 3)
        res["load_average_start"] = os.getloadavg()
        for k in range(a.pairs):
            pair = {}
            for name in ("fast", "default") if k % 2 == 0 else ("default", "fast"):
                out = str(Path(tmp) / f"out_{name}_{k}")
                if name == "fast":
                    r = run(d2turb + ["--preset", "fast", "--out", out])
                    r["frames"] = n
                    short = run(d2turb + ["--preset", "fast", "--max-frames", str(third), "--out", out + "s"])
                    r["marginal_frames_per_s"] = round((n - third) / max(r["wall_s"] - short["wall_s"], 1e-6), 2)
                    r["marginal_cpu_ms_per_frame"] = round(1000 * (r["cpu_s"] - short["cpu_s"]) / (n - third), 1)
                    r["short_run"] = short | {"frames": third}
                else:
                    r = run(d2turb + ["--max-frames", str(a.default_frames), "--out", out])
                    r["frames"] = min(n, a.default_frames)
                r["frames_per_s"] = round(r["frames"] / r["wall_s"], 2)
                r["cpu_ms_per_frame"] = round(1000 * r["cpu_s"] / r["frames"], 1)
                pair[name] = r
            res["pairs"].append(pair)
    rate = [p["fast"]["frames_per_s"] for p in res["pairs"]]
    base = [p["default"]["frames_per_s"] for p in res["pairs"]]
    res["summary"] = {"fast_frames_per_s": rate, "default_frames_per_s": base,
                      "speedup_paired": [round(x / y, 2) for x, y in zip(rate, base)]}  # fmt: skip
    text = json.dumps(res, indent=1)
    print(text)
    if a.json:
        Path(a.json).write_text(text + "\n")


if __name__ == "__main__":
    main()
