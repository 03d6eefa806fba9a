"""A stream's latency (issue 52 acceptance 4): windows that reach at most ``lookahead`` frames ahead over all the
registration rounds and the output (``ClipRestorer(lookahead=L)``, what ``restore -`` uses), counted in frames read
when each output comes out; the frames held stay bounded; a static scene stays within the noise and interpolation
bound through such windows. The pipe through the command line: tests/test_streams.py."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from d2turb.clip import ClipRestorer, PhysicsDeblur, window_start
from d2turb.clip.frames import lookahead_split, stream_lookahead
from d2turb.errors import D2TurbError

SIGMA = 0.02  # the frames' noise


def _scene(h: int = 64, w: int = 80, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.random((h, w, 3)).astype(np.float32), (0, 0), 2.5)
    return ((base - base.min()) / (base.max() - base.min())).astype(np.float32)


def _counted(scene: np.ndarray, n: int, log: list, seed: int = 1):
    """``n`` noisy frames of a static ``scene``; each index goes into ``log`` as it is read."""
    rng = np.random.default_rng(seed)
    for i in range(n):
        log.append(i)
        yield np.clip(scene + rng.normal(0, SIGMA, scene.shape).astype(np.float32), 0, 1)


def test_lookahead_split_deals_the_lookahead_over_the_levels_within_the_centred_reach():
    for temporal in (2, 3, 4, 8, 16, 32):
        centred = temporal - 1 - temporal // 2  # how far a centred window reaches past its frame
        for passes in (1, 2, 3):
            assert lookahead_split(None, temporal, passes) == [None] * (passes + 1)
            for lookahead in range((passes + 1) * centred + 3):
                ahead = lookahead_split(lookahead, temporal, passes)
                assert len(ahead) == passes + 1
                assert sum(ahead) == min(lookahead, (passes + 1) * centred)
                assert all(0 <= a <= centred for a in ahead) and max(ahead) - min(ahead) <= 1
    # a window reaching a frames ahead ends at index + a; reaching the centred reach, it is the centred window
    assert [window_start(20, 16, None, a) + 15 for a in (0, 3, 7)] == [20, 23, 27]
    assert window_start(20, 16, None, 7) == window_start(20, 16, None) == 12
    assert window_start(46, 16, 48, 3) == 32  # shifted inward at the clip's end (34 past it), as a centred one
    assert [stream_lookahead(t) for t in (2, 4, 16, 32)] == [0, 1, 7, 15]


@pytest.mark.parametrize(("temporal", "lookahead"), [(8, 3), (16, 7), (16, 0), (8, None)])
def test_an_output_comes_before_the_input_lookahead_plus_one_frames_later_is_read(temporal, lookahead):
    """Output t is yielded before input t + L + 1 is read (counted, no clock), once the first window is filled; the
    threaded restorer's deblur hands each output over when the next frame arrives: one frame more. Centred windows
    (None, a file's) wait for 3·(temporal/2 − 1) frames with two rounds: each level's window reaches temporal/2 − 1
    frames past its frame, and round k of a frame reads level k − 1 of its window."""
    n = 5 * temporal + 7
    bound = 3 * (temporal // 2 - 1) if lookahead is None else lookahead
    for threaded in (False, True):
        log: list[int] = []
        restorer = ClipRestorer(temporal=temporal, lookahead=lookahead, threaded=threaded, deblur=PhysicsDeblur(2.0))
        waits = []
        for out in restorer.restore(_counted(_scene(), n, log)):
            if out.index >= 2 * temporal and len(log) < n:  # steady: past the start, before the end is read
                waits.append(log[-1] - out.index)
        assert waits and max(waits) <= bound + threaded, (threaded, sorted(set(waits)))
        if not threaded:
            assert min(waits) == bound  # the windows do reach that far: no more latency than asked, no less


@pytest.mark.slow
def test_the_frames_held_stay_bounded_on_a_long_stream():
    """200 frames through windows of 16 reaching 7 ahead: at most temporal + lookahead + 1 frames are held at any
    time (from the oldest of the output's window, 16 − 1 − 3 behind, to the newest read, 7 ahead), whatever the length;
    centred windows hold more (they reach 21 ahead)."""
    temporal, lookahead = 16, 7
    held = {}
    for name, la in (("stream", lookahead), ("file", None)):
        restorer = ClipRestorer(temporal=temporal, lookahead=la, threaded=False, deblur=PhysicsDeblur(2.0))
        most, count = 0, 0
        for _ in restorer.restore(_counted(_scene(32, 40), 200, [])):
            most = max(most, len(restorer.state.frames))
            count += 1
        assert count == 200
        held[name] = most
    assert held["stream"] <= temporal + lookahead + 1
    assert held["stream"] < held["file"]


def test_a_static_scene_through_lookahead_windows_stays_within_the_noise_and_interpolation_bound():
    """A still camera on a still scene, noise σ = 0.02: every output of a stream's windows (16 frames, 7 ahead) is the
    scene within the mean's noise (σ/√16) plus what bilinear resampling at a registration error of 0.1 px
    smooths (the scene against itself shifted by 0.1 px both ways: the oracle's interpolation bound; centred windows
    measure 0.0046 here, against a bound of 0.0100)."""
    scene = _scene()
    tenth = np.float32([[1, 0, 0.1], [0, 1, 0.1]])
    shifted = cv2.warpAffine(scene, tenth, scene.shape[1::-1], flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    interpolation = float(np.sqrt(np.mean((shifted - scene)[4:-4, 4:-4] ** 2)))
    bound = SIGMA / 4 + interpolation
    restorer = ClipRestorer(temporal=16, lookahead=stream_lookahead(16), deblur="none", fusion="mean")
    errors = []
    for out in restorer.restore(_counted(scene, 48, [])):
        fused = out.fused.permute(1, 2, 0).numpy()
        errors.append(float(np.sqrt(np.mean((fused - scene)[4:-4, 4:-4] ** 2))))
    assert len(errors) == 48
    assert max(errors) <= bound, (max(errors), bound)


def test_lookahead_must_be_a_non_negative_integer():
    for bad in (-1, 2.5, True, "7"):
        with pytest.raises(D2TurbError, match="lookahead"):
            ClipRestorer(temporal=8, lookahead=bad)
