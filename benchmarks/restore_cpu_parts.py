"""CPU seconds of the parts of a clip restore, up to its first output and over the whole clip (issue 52 acceptance 3):
the imports, the frames read, each stage of the default restorer run serially (``threaded=False``) with one thread
for torch and OpenCV, and a PNG write. CPU time (``time.process_time``) rather than wall time: on a shared machine
it says what the work costs, not how long the machine made it wait.

Usage: ``OMP_WAIT_POLICY=PASSIVE python benchmarks/restore_cpu_parts.py CLIP [--temporal 16]`` (a folder of frames
or a video). Prints JSON lines: the imports, then the restorer to its first output and over the clip, then one line
per stage (seconds, calls, ms a call)."""

import time

_t0 = time.process_time()
import cv2  # noqa: E402
import numpy  # noqa: E402, F401
import PIL.Image  # noqa: E402, F401

try:
    import av  # noqa: F401  (the video extra: the mp4 writer)
except ImportError:  # pragma: no cover
    pass
_t1 = time.process_time()
import torch  # noqa: E402

_t2 = time.process_time()
import d2turb.restore.clips  # noqa: E402, F401

_t3 = time.process_time()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402
from types import SimpleNamespace  # noqa: E402

import d2turb.clip.blind as blind  # noqa: E402
import d2turb.clip.camera as camera  # noqa: E402
import d2turb.clip.pipeline as pipeline  # noqa: E402
import d2turb.clip.schedule as schedule  # noqa: E402
import d2turb.clip.stages as stages  # noqa: E402
from d2turb.io import write_image  # noqa: E402
from d2turb.restore.clip_build import clip_restorer  # noqa: E402
from d2turb.restore.clip_source import clip_frames  # noqa: E402

COST: dict[str, list] = {}


def timed(owner, attr: str, label: str) -> None:
    """Replace ``owner.attr`` by a wrapper that adds its CPU time to ``COST[label]``."""
    fn = getattr(owner, attr)

    def wrapper(*args, **kwargs):
        start = time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            cost = COST.setdefault(label, [0.0, 0])
            cost[0] += time.process_time() - start
            cost[1] += 1

    setattr(owner, attr, wrapper)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("clip", type=Path)
    p.add_argument("--temporal", type=int, default=16)
    a = p.parse_args()
    print(json.dumps({"import numpy, OpenCV, PIL, PyAV": round(_t1 - _t0, 3), "import torch": round(_t2 - _t1, 3),
                      "import the restore path": round(_t3 - _t2, 3)}))  # fmt: skip
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    start = time.process_time()
    _, it = clip_frames(a.clip, SimpleNamespace(record=print), as_stored=True)
    frames = list(it)
    COST["read the frames"] = [time.process_time() - start, len(frames)]
    timed(camera.CameraTrack, "place", "camera placement (CameraTrack.place)")
    timed(schedule, "register", "registration round (stages.register)")
    timed(schedule, "output_job", "fusion (stages.output_job)")
    timed(stages, "finish", "fallback and pose (stages.finish)")
    timed(blind.BlindDeblur, "decide", "the blind decision (BlindDeblur.decide)")
    timed(pipeline, "deblurred", "deblur and tone guard, with the decision (pipeline.deblurred)")
    restorer, _, _ = clip_restorer(a.clip, a.temporal)
    restorer.threaded = False
    start = time.process_time()
    outputs = restorer.restore(frames)
    next(outputs)
    first = time.process_time() - start
    count = 1 + sum(1 for _ in outputs)
    whole = time.process_time() - start
    print(json.dumps({"restorer to its first output": round(first, 3), f"restorer, {count} outputs": round(whole, 3)}))
    image = numpy.asarray(frames[0])
    with tempfile.TemporaryDirectory() as tmp:
        start = time.process_time()
        for i in range(10):
            write_image(os.path.join(tmp, f"{i}.png"), image)
        COST["write_image, PNG"] = [time.process_time() - start, 10]
    for label, (seconds, calls) in COST.items():
        print(json.dumps({"part": label, "cpu_s": round(seconds, 3), "calls": calls,
                          "ms_each": round(1000 * seconds / max(calls, 1), 1)}))  # fmt: skip


if __name__ == "__main__":
    main()
