"""d2turb.clip.schedule: in_order passes results on in order, a ready one before the next job is made; outputs
placing frames in a thread of their own computes the same outputs."""

import threading
from concurrent.futures import Future, ThreadPoolExecutor

import cv2
import numpy as np

from d2turb.clip.fusion import make_fusion
from d2turb.clip.schedule import in_order, outputs
from d2turb.clip.state import ClipState


def test_a_ready_value_is_passed_on_before_the_next_job_is_made():
    made = []

    def jobs():
        for i in range(3):
            made.append(i)
            yield i * 10

    it = in_order(jobs())
    assert next(it) == 0 and made == [0]  # the first output does not wait for the second to be computed
    assert list(it) == [10, 20] and made == [0, 1, 2]


def test_futures_keep_their_order_with_one_more_in_flight():
    futures = [Future() for _ in range(3)]
    first_done_when_second_asked = []

    def jobs():
        yield futures[0]
        first_done_when_second_asked.append(futures[0].done())
        futures[0].set_result("a")
        yield futures[1]
        futures[1].set_result("b")
        yield futures[2]
        futures[2].set_result("c")

    assert list(in_order(jobs())) == ["a", "b", "c"]
    assert first_done_when_second_asked == [False]  # the next job is made while the first is still running


def test_a_finished_future_is_passed_on_at_once():
    done = Future()
    done.set_result("x")
    made = []

    def jobs():
        made.append(0)
        yield done
        made.append(1)
        yield "y"

    it = in_order(jobs())
    assert next(it) == "x" and made == [0]
    assert list(it) == ["y"]


def test_what_is_queued_when_the_caller_stops_is_cancelled():
    first, queued, never = Future(), Future(), Future()

    def jobs():
        yield first
        first.set_result("a")
        yield queued
        yield never

    it = in_order(jobs())
    assert next(it) == "a"
    it.close()
    assert queued.cancelled() and not never.cancelled()  # the one made is cancelled; the next was never asked for


def _shaken_clip(n=20, h=48, w=56, seed=0):
    """A smooth random scene, shifted by a random sub-pixel jitter and a 5-px jump mid-clip, 8-bit."""
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.random((h + 24, w + 24, 3)).astype(np.float32), (0, 0), 2)
    frames = []
    for t in range(n):
        dx, dy = rng.normal(0, 1, 2) + (5 if t >= n // 2 else 0)
        m = np.float32([[1, 0, 12 + dx], [0, 1, 12 + dy]])
        f = cv2.warpAffine(base, m, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        frames.append(np.rint(np.clip(f, 0, 1) * 255).astype(np.uint8))
    return frames


def test_placing_frames_in_a_thread_of_their_own_changes_no_output():
    frames = _shaken_clip()
    held_in = []

    def run(pool):
        state = ClipState(8, 2, make_fusion("mean"), "fast", True)
        hold = state.hold
        state.hold = lambda item: (held_in.append(threading.current_thread().name), hold(item))[1]
        return [(f.fused.numpy().copy(), f.camera_px) for f in outputs(state, frames, True, hold_pool=pool)]

    serial = run(None)
    assert set(held_in) == {threading.current_thread().name}
    held_in.clear()
    with ThreadPoolExecutor(1, thread_name_prefix="placing") as pool:
        threaded = run(pool)
    assert held_in and all(name.startswith("placing") for name in held_in)
    assert len(serial) == len(threaded) == len(frames)
    for (a, pose_a), (b, pose_b) in zip(serial, threaded):
        assert np.array_equal(a, b) and pose_a == pose_b
