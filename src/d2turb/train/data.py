"""Training data of one process: the dataset (pairs on disk, clean images or an in-memory pack), the on-the-fly
synthesis of turbulent pairs on the training device, and the loader over this rank's resumable share."""

from __future__ import annotations

import warnings
from pathlib import Path

import torch
from torch.utils.data import DataLoader, Dataset

from d2turb.data import CleanCropDataset, OnTheFlySynthesis, PairDataset
from d2turb.data.pack_read import PackCrops
from d2turb.data.split import split_of
from d2turb.errors import D2TurbError
from d2turb.sim import Simulator
from d2turb.sim.geometry import geometry_bank
from d2turb.train.config import Config
from d2turb.train.distributed import ResumableSampler


class SynthesisFactory:
    """``(bins, seed) -> OnTheFlySynthesis`` on ``device`` for ``cfg.data.on_the_fly``; one set of simulators
    (built on first use) is shared by every synthesis it makes (training and pack validation)."""

    def __init__(self, cfg: Config, device: torch.device) -> None:
        self.otf, self.device = cfg.data.on_the_fly, device
        self.simulators: list[Simulator] | None = None

    def __call__(self, bins, seed: int) -> OnTheFlySynthesis:
        if self.simulators is None:
            bank = geometry_bank(self.otf.geometry, self.otf.params or {})
            self.simulators = [Simulator(p, self.device) for p in bank]
        return OnTheFlySynthesis(
            self.simulators, bins=tuple(bins), device=self.device, seed=seed, use_depth=self.otf.depth != "none"
        )


def build_dataset(
    cfg: Config, rank: int, device: torch.device, aug_seed: int, make_synthesis: SynthesisFactory, warn: bool
) -> tuple[Dataset, OnTheFlySynthesis | None]:
    """The training dataset and its synthesis.

    Args:
        cfg: the run's config (``data``; ``train.seed``).
        rank: this process's rank (the synthesis seed is ``train.seed + rank``).
        device: the training device (a pack's crops and every synthesis live there).
        aug_seed: seed of a pack's crop and flip generator (this rank's augmentation stream).
        make_synthesis: the trainer's synthesis factory.
        warn: warn when ``data.clean`` holds test folders of the fixed split (rank 0).

    Returns:
        (dataset: CPU items, or device items for a pack; synthesis: None for pairs).
    """
    data, otf = cfg.data, cfg.data.on_the_fly
    if data.source == "pairs":
        probe = PairDataset(data.pairs)
        return PairDataset(data.pairs, crop=min(data.patch, probe.patch), hflip=data.hflip, vflip=data.vflip), None
    if data.source == "clean":
        tests = sorted({Path(c).name for c in data.clean if split_of(c) == "test"})
        if tests and warn:
            warnings.warn(
                f"data.clean includes test folder(s) {', '.join(tests)} of the fixed split (d2turb.data.split)",
                stacklevel=3,  # the Trainer(...) line
            )
        dataset = CleanCropDataset(
            data.clean, patch=data.patch, depth_spec=otf.depth, length=otf.length, hflip=data.hflip
        )
    else:
        dataset = PackCrops(
            data.pack,
            patch=data.patch,
            split="train",
            length=otf.length,
            hflip=data.hflip,
            vflip=data.vflip,
            depth=otf.depth,
            device=device,
            seed=aug_seed,
        )
    return dataset, make_synthesis(otf.bins, cfg.train.seed + rank)


class TrainingData:
    """The training data of one process: dataset, synthesis, this rank's resumable share and its loader.

    Args:
        cfg: the run's config (``data``; ``train.seed``).
        rank: this process's rank.
        world: the number of processes.
        device: the training device.
        batch: the per-process batch size.
        aug_seed: seed of this rank's augmentation stream (a pack's crops and flips).
        warn: warn about questionable data settings (rank 0).

    Attributes:
        dataset, synthesis (None for pairs), make_synthesis (:class:`SynthesisFactory`, shared with validation),
        sampler (:class:`~d2turb.train.distributed.ResumableSampler`), loader_generator (the loader's shuffling
        generator, seeded ``train.seed + rank``), loader, iters_per_epoch (full batches per epoch).
    """

    def __init__(
        self, cfg: Config, rank: int, world: int, device: torch.device, batch: int, aug_seed: int, warn: bool
    ) -> None:
        self.device = device
        self.make_synthesis = SynthesisFactory(cfg, device)
        self.dataset, self.synthesis = build_dataset(cfg, rank, device, aug_seed, self.make_synthesis, warn)
        self.sampler = ResumableSampler(self.dataset, world, rank, cfg.train.seed)
        self.iters_per_epoch = len(self.sampler) // batch
        if self.iters_per_epoch < 1:
            raise D2TurbError(
                f"the training set has {len(self.dataset)} samples, fewer than one batch of {batch} per process"
            )
        self.loader_generator = torch.Generator().manual_seed(cfg.train.seed + rank)
        in_memory = cfg.data.source == "pack"  # device tensors: no workers, no pinning
        self.loader = DataLoader(
            self.dataset,
            batch_size=batch,
            sampler=self.sampler,
            drop_last=True,
            num_workers=0 if in_memory else cfg.data.num_workers,
            generator=self.loader_generator,
            pin_memory=device.type == "cuda" and not in_memory,
        )

    def to_device(self, batch: dict) -> dict:
        """A loader batch on the training device: synthesised from its clean images, or moved there (pairs)."""
        if self.synthesis is not None:
            return self.synthesis(batch)
        return {k: v.to(self.device, non_blocking=True) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
