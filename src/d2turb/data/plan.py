"""What each sample of make-dataset draws, from the dataset seed and its own index (or its chunk's) alone: its source
image, crop and D/r0 (:func:`plan_sample`), its chunk's imaging geometry and simulator seed. This is what makes the
output independent of the number of processes and of restarts (:mod:`~d2turb.data.generate`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from d2turb.data.layout import sample_id
from d2turb.sim.params import bin_spans, dr0_bin, dr0_from_uniform


@dataclass
class SamplePlan:
    index: int
    id: str
    source: int  # index into the sorted source list
    dr0: float
    bin: str
    crop_u: float  # crop offsets as fractions of the free range, resolved once the image size is known
    crop_v: float


def keyed_rng(*key: int) -> np.random.Generator:
    """numpy's generator of the integer key (seed, stream, index): the same key, the same draws."""
    return np.random.default_rng(np.random.SeedSequence([int(k) for k in key]))


def chunk_geometry(seed: int, chunk: int, n_geometries: int) -> int:
    """Index of the imaging geometry of chunk ``chunk`` (from (seed, chunk) only)."""
    return int(keyed_rng(seed, 2, chunk).integers(n_geometries)) if n_geometries > 1 else 0


def chunk_seed(seed: int, chunk: int) -> int:
    """Simulator seed of chunk ``chunk`` (63-bit, from (seed, chunk) only)."""
    return int(np.random.SeedSequence([int(seed), 1, int(chunk)]).generate_state(1, np.uint64)[0] >> np.uint64(1))


def plan_sample(index: int, seed: int, split: str, bins: tuple[str, ...], n_sources: int) -> SamplePlan:
    """Everything random about sample ``index`` except the simulator noise, from (seed, index) only.

    test: bin = bins[i % n_bins], D/r0 uniform inside it, source = (i // n_bins) % n_sources (each image
    appears once per bin before any repeats); train: D/r0 uniform over the union of bins, random source.
    """
    rng = keyed_rng(seed, 0, index)
    if split == "test":
        name = bins[index % len(bins)]
        dr0 = float(dr0_from_uniform(rng.random(), bin_spans([name])))
        source = (index // len(bins)) % n_sources
    else:
        dr0 = float(dr0_from_uniform(rng.random(), bin_spans(bins)))
        name = dr0_bin(dr0)
        source = int(rng.integers(n_sources))
    u, v = rng.random(2)
    return SamplePlan(index, sample_id(index), source, dr0, name, float(u), float(v))


def crop_box(plan: SamplePlan, height: int, width: int, patch: int) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) of the patch inside a height×width image."""
    x0 = min(int(plan.crop_u * (width - patch + 1)), width - patch)
    y0 = min(int(plan.crop_v * (height - patch + 1)), height - patch)
    return x0, y0, x0 + patch, y0 + patch
