"""The fusions of a window's registered frames, by name (``--fusion``): a registry, as the models have theirs
(:func:`register_fusion`, :func:`make_fusion`). A fusion is an object made afresh for each clip (it may keep state
from window to window: the sharpest fusion's current choice) that says what it reads and where it runs; the clip
room (:class:`~d2turb.clip.pipeline.ClipRestorer`) asks nothing else of it. The algorithms live beside it:
:mod:`d2turb.clip.fba`, :mod:`d2turb.clip.sharpest`."""

from __future__ import annotations

import concurrent.futures
import functools
from collections.abc import Callable

import numpy as np

from d2turb.clip.fba import fourier_burst_accumulation
from d2turb.clip.frames import HeldFrame, as_float
from d2turb.clip.sharpest import SharpestFusion, coarse_grey, sharp_coefficients
from d2turb.errors import D2TurbError

# The physics deblur after the sharpest fusion: each coefficient comes from the frame that kept it best, so what is
# left is the blur of a weaker turbulence than the mean short-exposure one: the Wiener filter uses the OTF at
# D/r0 × SHARPEST_DR0_SCALE (chosen on the validation clips, docs/clips.md) and the Laplacian prior: the selection
# keeps noise that the gradient prior lets through (24 validation clips: −1.7 / −1.1 / −1.2 dB against it).
SHARPEST_DR0_SCALE = 0.3  # 0.6 / 0.5 / 0.4 / 0.3: 0.3 best in every bin (docs/clips.md), still below the mean + Wiener

FUSION_REGISTRY: dict[str, type[Fusion]] = {}


def register_fusion(cls: type[Fusion]) -> type[Fusion]:
    """Class decorator: make ``cls`` available as ``--fusion cls.name``."""
    if not cls.name or cls.name in FUSION_REGISTRY:
        raise ValueError(f"a fusion needs a new name, got {cls.name!r}")
    FUSION_REGISTRY[cls.name] = cls
    return cls


def make_fusion(name: str) -> Fusion:
    """A fresh fusion ``name`` for one clip; D2TurbError for an unknown name."""
    if name not in FUSION_REGISTRY:
        raise D2TurbError(f"unknown fusion {name!r}; choose one of {', '.join(FUSION_REGISTRY)}")
    return FUSION_REGISTRY[name]()


def fusion_class(name: str) -> type[Fusion]:
    """The class registered as ``name`` (its attributes, without making one); D2TurbError for an unknown name."""
    if name not in FUSION_REGISTRY:
        raise D2TurbError(f"unknown fusion {name!r}; choose one of {', '.join(FUSION_REGISTRY)}")
    return FUSION_REGISTRY[name]


class Fusion:
    """What a fusion provides to the clip room.

    Attributes:
        name: its ``--fusion`` name.
        reads_mean: :meth:`fuse` is given the window's mean of the registered frames (a running sum the clip room
            keeps); otherwise None.
        threaded: :meth:`fuse` returns a call that the clip room runs in a thread of its own (one output in flight,
            the next frames register meanwhile), and :meth:`prepare`'s work goes to another.
        moving_against_mean: the moving-object test compares each frame with the window's mean, not with the fusion
            (a fusion whose own detail would inflate the frame's residual scale and hide the objects).
        deblur_dr0_scale, deblur_prior: the blur left after it, as a deblur models it (the OTF at D/r0 × this scale;
            the blind deblur's Wiener prior).
    """

    name: str = ""
    reads_mean = True
    threaded = False
    moving_against_mean = False
    deblur_dr0_scale = 1.0
    deblur_prior = "gradient"

    def prepare(self, frame: HeldFrame, window: list[HeldFrame], level: int, submit: Callable) -> None:
        """Called once ``frame``'s last registration round is held (``frame.warped[-1]``); ``window``: the frames of
        its window, whose level ``level`` the round's reference averaged; ``submit(call)`` runs a call now or in the
        fusion's thread (a Future). What it prepares goes to ``frame.prepared``."""

    def fuse(self, window: dict[int, HeldFrame], mean: np.ndarray | None):
        """The fusion of ``window``'s last-round images (frame index → frame, in order), (H,W,C) float32 in [0, 1],
        the clip room's own (it changes it in place); a threaded fusion may return a call that makes it. ``mean``:
        the window's mean (``reads_mean``)."""
        raise NotImplementedError


@register_fusion
class MeanFusion(Fusion):
    """The window's plain mean (its blur is the mean short-exposure OTF that the Wiener filter models)."""

    name = "mean"

    def fuse(self, window, mean):
        return mean


@register_fusion
class RobustFusion(Fusion):
    """Per-pixel weights 1/(1 + (r/2τ)²) of each frame's residual r against the mean, τ its robust scale."""

    name = "robust"

    def fuse(self, window, mean):
        num = np.zeros_like(mean)
        den = np.zeros(mean.shape[:2] + (1,), dtype=np.float32)
        for img in (as_float(f.warped[-1]) for f in window.values()):
            r = np.abs(img - mean).mean(axis=2, keepdims=True)
            tau = max(1.4826 * float(np.median(r)), 1e-3)
            w = 1.0 / (1.0 + (r / (2.0 * tau)) ** 2)
            num += w * img
            den += w
        return num / den


@register_fusion
class FBAFusion(Fusion):
    """Fourier burst accumulation: each frequency mostly from the frames that kept it best (:mod:`d2turb.clip.fba`)."""

    name = "fba"
    reads_mean = False

    def fuse(self, window, mean):
        return fourier_burst_accumulation([as_float(f.warped[-1]) for f in window.values()])


@register_fusion
class SharpestCoefficientFusion(Fusion):
    """Per coefficient the frame that kept it best (:mod:`d2turb.clip.sharpest`); where no frame may be chosen, the
    window's plain mean, which is also what moving objects are found against (the fusion's own detail would inflate
    the robust scale of the frame's residual and hide them: dost_street_clip, half a car ghosted)."""

    name = "sharpest"
    threaded = True
    moving_against_mean = True
    deblur_dr0_scale = SHARPEST_DR0_SCALE
    deblur_prior = "laplacian"

    def __init__(self):
        self.choice = SharpestFusion()  # the window's current choice, updated from output to output

    def prepare(self, frame, window, level, submit):
        # each frame's outliers against the median of the window's frames (coarse grey of the reference's level)
        for f in window:
            if f.coarse is None:
                f.coarse = coarse_grey(f.level_float(level))
        median = np.median(np.stack([f.coarse for f in window]), axis=0)
        # as held: uint8 or float16; with a thread, computed there (a Future, which the fusion waits for)
        frame.prepared = submit(functools.partial(sharp_coefficients, frame.warped[-1], median))

    def fuse(self, window, mean):
        held = {j: f.prepared for j, f in window.items()}
        return functools.partial(self._fuse, held, mean)

    def _fuse(self, held: dict, mean: np.ndarray) -> np.ndarray:
        coefficients = {j: c.result() if isinstance(c, concurrent.futures.Future) else c for j, c in held.items()}
        return self.choice.fuse(coefficients, mean)
