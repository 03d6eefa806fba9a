"""Where the time of a clip restore goes, stage by stage (issue 52 item 1): the default restorer run serially
(``ClipRestorer(threaded=False)``: every stage in one thread, so a profile's cumulative times add up) under cProfile,
one thread for OpenCV and torch, on the first ``--frames`` frames of a clip (read before the clock starts).

Usage: ``python benchmarks/clip_profile.py CLIP [--frames 24] [--temporal 16] [--out profile.json]``. Prints and
writes seconds per frame of each stage's function (cumulative: a stage includes what it calls)."""

import argparse
import cProfile
import itertools
import json
import pstats
import time
from pathlib import Path
from types import SimpleNamespace

import cv2
import torch

# the stages, by the function that is each one (module path fragment, function name)
STAGES = {
    "read + place on the canvas (ClipState.hold)": ("clip/state.py", "hold"),
    "registration rounds (stages.register)": ("clip/stages.py", "register"),
    "  of which DIS dense flow": ("clip/registration.py", "__call__"),
    "  of which remap": ("clip/registration.py", "remap"),
    "  of which the running references": ("clip/state.py", "reference"),
    "output: fusion, fallback, pose (stages.finish)": ("clip/stages.py", "finish"),
    "  of which the moving-object share": ("clip/stages.py", "fallback_share"),
    "  of which the move to the output pose": ("clip/camera.py", "apply"),
    "deblur + tone guard (ClipRestorer._deblurred)": ("clip/pipeline.py", "_deblurred"),
    "  of which the blind deblur's decision": ("clip/blind.py", "decide"),
    "  of which the tone guard": ("clip/deblur.py", "tone_guard"),
    "release (ClipState.release)": ("clip/state.py", "release"),
}


def main() -> None:
    from d2turb.restore.clip_build import clip_restorer
    from d2turb.restore.clip_source import clip_frames

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("clip", type=Path)
    p.add_argument("--frames", type=int, default=24)
    p.add_argument("--temporal", type=int, default=16)
    p.add_argument("--out", type=Path)
    a = p.parse_args()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    _, it = clip_frames(a.clip, SimpleNamespace(record=print), as_stored=True)
    frames = list(itertools.islice(it, a.frames))
    restorer, name, _ = clip_restorer(a.clip, a.temporal)
    restorer.threaded = False
    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.enable()
    count = sum(1 for _ in restorer.restore(frames))
    prof.disable()
    wall = time.perf_counter() - t0
    stats = pstats.Stats(prof).stats
    rows = {}
    for label, (path, func) in STAGES.items():
        cum = sum(v[3] for (f, _, fn), v in stats.items() if f.endswith(path) and fn == func)
        rows[label] = cum / count
    shape = frames[0].shape if hasattr(frames[0], "shape") else None
    result = {"clip": str(a.clip), "frames": count, "shape": list(shape), "temporal": a.temporal, "deblur": name,
              "seconds_per_frame": wall / count, "stages_seconds_per_frame": rows}  # fmt: skip
    print(json.dumps(result, indent=1))
    if a.out:
        a.out.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
